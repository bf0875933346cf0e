//! Coalescing the encoder runs of the scorers that share a model into batches.
//!
//! Each batching scorer is a **member** of its model's [`Batcher`]. A frame is queued; the
//! model's batch worker (one thread per batching model while it has members; an idle worker
//! waits 30 s for the next model, so that models coming and going reuse it; it holds the model
//! only while it runs a batch, so that the model's last scorer frees it) waits at most the
//! first queued frame's `batch_timeout` until every *streaming* member has a frame queued (at
//! most its `batch_size`), runs them as one batch and hands each its features.
//!
//! One thread runs every batch of a model so that ONNX Runtime's memory for the batches (its
//! arena grows with the batch size) is allocated and freed by one thread. When whichever
//! member's streaming thread happened to lead ran the batch, each model's arena grew on another
//! thread, and the C allocator kept the freed blocks in as many per-thread arenas: creating and
//! destroying elements with mixed batch sizes grew the resident memory round after round
//! (issue 22, item 4; `tests/churn_memory.rs`).
//!
//! What "streaming" means: a member streams from the moment it queues a frame. It stops counting
//! (the others no longer wait for it) when
//! - it says so ([`Batcher::idle`]: EOS, PAUSED, a flush or stop of its element), or when it
//!   leaves ([`Batcher::leave`], its scorer dropped);
//! - a batch's wait ran out (`batch_timeout`) without a frame from it: a stream whose sink stopped
//!   pulling, or that has no frame for now. Its next frame counts it in again.
//!
//! So a stream that went idle costs the others at most one `batch_timeout`, once, instead of one
//! per batch; a slow but live stream keeps joining batches (each of its frames counts it in, and
//! the others wait for it at most `batch_timeout`, as for any member). A frame queued by a member
//! that has since stopped streaming runs at once, without waiting for the others.

use std::collections::HashMap;
use std::sync::{Condvar, Mutex, MutexGuard};
use std::time::{Duration, Instant};

use super::{lock, Features};

/// One queued frame, with its member's batch settings.
pub(super) struct Job {
    ticket: u64,
    member: u64,
    batch_size: usize,
    timeout: Duration,
    pub(super) image: Vec<f32>,
}

impl Job {
    /// A frame that is not queued: for a dry run of [`super::run_batch`] at load.
    pub(super) fn unqueued(image: Vec<f32>) -> Job {
        Job {
            ticket: 0,
            member: 0,
            batch_size: 0,
            timeout: Duration::ZERO,
            image,
        }
    }
}

#[derive(Default)]
pub(super) struct Batcher {
    state: Mutex<BatchState>,
    cv: Condvar,
}

#[derive(Default)]
struct BatchState {
    queue: Vec<Job>,
    /// Every member, and whether it is streaming.
    members: HashMap<u64, bool>,
    next_member: u64,
    next_ticket: u64,
    /// The batch worker runs.
    worker: bool,
    /// Each finished frame's features, and its image buffer back for reuse.
    done: HashMap<u64, (Result<Features, String>, Vec<f32>)>,
    /// The batched input, reused.
    input: Vec<f32>,
    /// Batches run and frames in them (for tests and benchmarks).
    batches: u64,
    frames: u64,
}

impl BatchState {
    fn streaming(&self, member: u64) -> bool {
        self.members.get(&member).copied().unwrap_or(false)
    }

    /// Whether the queued frames should run now: every streaming member (up to `batch_size`)
    /// has one queued, or one was queued by a member that has stopped streaming since.
    fn ready(&self, batch_size: usize) -> bool {
        let streaming = self.members.values().filter(|&&s| s).count();
        let (mut from_streaming, mut from_idle) = (0, false);
        for j in &self.queue {
            if self.streaming(j.member) {
                from_streaming += 1;
            } else {
                from_idle = true;
            }
        }
        self.queue.len() >= batch_size || from_idle || from_streaming >= streaming.min(batch_size)
    }

    /// The wait ran out: the streaming members with no frame queued stop counting until their
    /// next frame.
    fn timed_out(&mut self) {
        let queued: Vec<u64> = self.queue.iter().map(|j| j.member).collect();
        for (id, streaming) in self.members.iter_mut() {
            if !queued.contains(id) {
                *streaming = false;
            }
        }
    }
}

impl Batcher {
    fn state(&self) -> MutexGuard<'_, BatchState> {
        lock(&self.state)
    }

    /// A new member; it counts as streaming from its first frame. `spawn` starts the batch
    /// worker (a thread that calls [`Batcher::serve`]) when none runs; `None` if it could not.
    pub(super) fn join(&self, spawn: impl FnOnce() -> std::io::Result<()>) -> Option<u64> {
        let mut st = self.state();
        if !st.worker {
            spawn().ok()?;
            st.worker = true;
        }
        let id = st.next_member;
        st.next_member += 1;
        st.members.insert(id, false);
        Some(id)
    }

    /// The member is gone: the others stop waiting for it.
    pub(super) fn leave(&self, member: u64) {
        self.state().members.remove(&member);
        self.cv.notify_all();
    }

    /// The member stops streaming for now (EOS, PAUSED, flush, stop): the others stop waiting
    /// for it, and a frame of its own already queued runs without waiting for theirs. Its next
    /// frame counts it in again.
    pub(super) fn idle(&self, member: u64) {
        if let Some(s) = self.state().members.get_mut(&member) {
            *s = false;
        }
        self.cv.notify_all();
    }

    /// Batches run so far, and the frames in them.
    pub(super) fn counts(&self) -> (u64, u64) {
        let st = self.state();
        (st.batches, st.frames)
    }

    /// Members, and how many of them count as streaming (for tests).
    pub(super) fn members(&self) -> (usize, usize) {
        let st = self.state();
        (
            st.members.len(),
            st.members.values().filter(|&&s| s).count(),
        )
    }

    /// Queue `image` for `member` and wait for its features, computed in a batch by the worker;
    /// `image` comes back with them, to be reused (no allocation per frame in the streaming
    /// thread).
    pub(super) fn encode(
        &self,
        member: u64,
        batch_size: usize,
        timeout: Duration,
        image: Vec<f32>,
    ) -> (Result<Features, String>, Vec<f32>) {
        let mut st = self.state();
        let ticket = st.next_ticket;
        st.next_ticket += 1;
        st.queue.push(Job {
            ticket,
            member,
            batch_size: batch_size.max(1),
            timeout,
            image,
        });
        if let Some(s) = st.members.get_mut(&member) {
            *s = true;
        }
        self.cv.notify_all();
        loop {
            if let Some(r) = st.done.remove(&ticket) {
                return r;
            }
            st = self.cv.wait(st).unwrap_or_else(|e| e.into_inner());
        }
    }

    /// The batch worker: collect and run batches until the last member leaves. `run` computes
    /// the features of a batch (`jobs` in order, `input` a buffer to reuse for the batched
    /// tensor).
    pub(super) fn serve(
        &self,
        run: impl Fn(&[Job], &mut Vec<f32>) -> Result<Vec<Features>, String>,
    ) {
        let mut st = self.state();
        loop {
            if st.members.is_empty() {
                st.worker = false;
                return;
            }
            let Some((batch_size, timeout)) = st.queue.first().map(|j| (j.batch_size, j.timeout))
            else {
                st = self.cv.wait(st).unwrap_or_else(|e| e.into_inner());
                continue;
            };
            let deadline = Instant::now() + timeout;
            while !st.ready(batch_size) {
                let now = Instant::now();
                if now >= deadline {
                    st.timed_out();
                    break;
                }
                st = self
                    .cv
                    .wait_timeout(st, deadline - now)
                    .unwrap_or_else(|e| e.into_inner())
                    .0;
            }
            let take = st.queue.len().min(batch_size);
            let jobs: Vec<Job> = st.queue.drain(..take).collect();
            let mut input = std::mem::take(&mut st.input);
            drop(st);
            let results =
                std::panic::catch_unwind(std::panic::AssertUnwindSafe(|| run(&jobs, &mut input)))
                    .unwrap_or_else(|_| Err("the batch run panicked".into()));
            st = self.state();
            st.input = input;
            st.batches += 1;
            st.frames += jobs.len() as u64;
            let results = match results {
                Ok(feats) if feats.len() == jobs.len() => feats.into_iter().map(Ok).collect(),
                Ok(feats) => {
                    let e = format!("{} features for a batch of {}", feats.len(), jobs.len());
                    vec![Err(e); jobs.len()]
                }
                Err(e) => vec![Err(e); jobs.len()],
            };
            for (j, r) in jobs.into_iter().zip(results) {
                st.done.insert(j.ticket, (r, j.image));
            }
            self.cv.notify_all();
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn queued(st: &mut BatchState, member: u64) {
        st.queue.push(Job {
            ticket: st.next_ticket,
            member,
            batch_size: 4,
            timeout: Duration::ZERO,
            image: Vec::new(),
        });
        st.next_ticket += 1;
        st.members.insert(member, true);
    }

    /// A batcher's state with members 0..n, all streaming.
    fn streaming(n: u64) -> BatchState {
        let mut st = BatchState::default();
        for m in 0..n {
            st.members.insert(m, true);
        }
        st
    }

    #[test]
    fn waits_for_every_streaming_member_up_to_the_batch_size() {
        let mut st = streaming(4);
        queued(&mut st, 0);
        assert!(!st.ready(4));
        queued(&mut st, 1);
        queued(&mut st, 2);
        assert!(!st.ready(4));
        assert!(st.ready(3), "a full batch runs");
        queued(&mut st, 3);
        assert!(st.ready(4));
    }

    #[test]
    fn members_not_streaming_are_not_waited_for() {
        let mut st = BatchState::default();
        st.members.insert(0, true);
        // Joined, no frame yet: not streaming.
        st.members.insert(1, false);
        queued(&mut st, 0);
        assert!(st.ready(4));
    }

    #[test]
    fn a_timeout_drops_the_members_that_sent_nothing_until_their_next_frame() {
        let mut st = streaming(3);
        queued(&mut st, 0);
        queued(&mut st, 1);
        assert!(!st.ready(4));
        st.timed_out();
        assert!(st.members[&0]);
        assert!(!st.members[&2]);
        st.queue.clear();
        queued(&mut st, 0);
        queued(&mut st, 1);
        assert!(st.ready(4), "member 2 is not waited for any more");
        queued(&mut st, 2);
        st.queue.clear();
        queued(&mut st, 0);
        assert!(!st.ready(4), "member 2's frame counted it in again");
    }

    #[test]
    fn a_frame_of_a_member_that_went_idle_runs_at_once() {
        let mut st = streaming(3);
        queued(&mut st, 0);
        assert!(!st.ready(4));
        st.members.insert(0, false);
        assert!(st.ready(4));
    }

    #[test]
    fn members_join_idle_and_stream_from_their_first_frame() {
        let b = std::sync::Arc::new(Batcher::default());
        let spawn = || {
            let b = b.clone();
            std::thread::Builder::new()
                .spawn(move || {
                    b.serve(|jobs, _| {
                        Ok(jobs
                            .iter()
                            .map(|j| Features {
                                shape: vec![1],
                                data: j.image.clone(),
                            })
                            .collect())
                    })
                })
                .map(|_| ())
        };
        let a = b.join(spawn).unwrap();
        let c = b.join(|| panic!("one worker")).unwrap();
        assert_eq!(b.members(), (2, 0));
        // `c` does not stream yet: no wait for it.
        let (f, back) = b.encode(a, 4, Duration::from_secs(5), vec![1.0]);
        assert_eq!(f.unwrap().data, vec![1.0]);
        assert_eq!(back, vec![1.0], "the image buffer comes back");
        assert_eq!(b.members(), (2, 1));
        b.idle(a);
        assert_eq!(b.members(), (2, 0));
        b.leave(c);
        assert_eq!(b.members(), (1, 0));
        assert_eq!(b.counts(), (1, 1));
        b.leave(a);
        let t = Instant::now();
        while b.state().worker {
            assert!(
                t.elapsed() < Duration::from_secs(5),
                "the worker ends with the last member"
            );
            std::thread::sleep(Duration::from_millis(1));
        }
    }
}

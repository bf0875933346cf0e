//! Running statistics and the typed `leangate-stats` bus message.

/// Name of the element message with running statistics.
pub const STATS_MESSAGE: &str = "leangate-stats";

/// The `leangate-stats` element message, typed. [`StatsMessage::to_structure`] is what the element
/// posts; [`StatsMessage::from_structure`] is how applications (and `leangate eval`) read it back.
#[derive(Debug, Clone, PartialEq)]
pub struct StatsMessage {
    /// Frames received since start.
    pub frames_in: u64,
    /// Frames kept since start.
    pub frames_kept: u64,
    /// Frames the model did not run on: the geometric prior alone bounded their utility below the
    /// threshold (`screen`; dropped unless warmup, max-gap or a forced keyframe kept them).
    pub frames_screened: u64,
    /// Frames dropped because they carry no usable picture (dark, saturated, noise;
    /// `reject-junk`).
    pub frames_junk: u64,
    /// `frames_kept / frames_in` (0 before the first frame).
    pub keep_ratio: f64,
    /// Mean preprocessing + inference time per scored frame, microseconds.
    pub inference_mean_us: f64,
    /// Median of that time, microseconds (to within about 3 %: a bounded histogram).
    pub inference_p50_us: u64,
    /// 99th percentile of that time, microseconds (to within about 3 %).
    pub inference_p99_us: u64,
    /// Frames received since the previous `leangate-stats` message (or start).
    pub interval_frames_in: u64,
    /// Frames kept since the previous `leangate-stats` message (or start).
    pub interval_frames_kept: u64,
    /// Frames screened (see `frames_screened`) since the previous message (or start).
    pub interval_frames_screened: u64,
    /// Mean inference time over the frames scored since the previous message, microseconds.
    pub interval_inference_mean_us: f64,
    /// Median inference time since the previous message, microseconds.
    pub interval_inference_p50_us: u64,
    /// 99th percentile inference time since the previous message, microseconds.
    pub interval_inference_p99_us: u64,
    /// The execution provider in use (`cpu`, `cuda`, `tensorrt`).
    pub execution_provider: String,
    /// The model's name.
    pub model: String,
    /// `model-precision`: the arithmetic of the graph that runs (`fp32`, `int8`).
    pub model_precision: String,
    /// The threshold in force.
    pub threshold: f64,
    /// What the consumer's `leangate-feedback` adds to the utility now (0 without feedback).
    pub feedback_offset: f64,
    /// Remote scoring only (the `server` property set): the `server-*` fields.
    pub server: Option<ServerStats>,
}

/// The `server-*` fields of `leangate-stats`, present when frames are scored on a server.
#[derive(Debug, Clone, PartialEq, Eq, Default)]
pub struct ServerStats {
    /// `server`: the server's URL.
    pub server: String,
    /// `server-model`: the model's name on the server.
    pub server_model: String,
    /// `server-requests`: inference requests sent since start.
    pub requests: u64,
    /// `server-failed-requests`: those that failed (unreachable, timeout, error status).
    pub failed_requests: u64,
    /// `server-latency-p50-us`: median round trip of the successful requests, microseconds.
    pub latency_p50_us: u64,
    /// `server-latency-p99-us`: 99th percentile of that round trip, microseconds.
    pub latency_p99_us: u64,
}

/// A `leangate-stats` structure that lacks a field or has one of the wrong type.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
#[error("not a valid {STATS_MESSAGE} structure: {0}")]
pub struct StatsParseError(String);

impl StatsMessage {
    pub fn to_structure(&self) -> gst::Structure {
        gst::Structure::builder(STATS_MESSAGE)
            .field("frames-in", self.frames_in)
            .field("frames-kept", self.frames_kept)
            .field("frames-screened", self.frames_screened)
            .field("frames-junk", self.frames_junk)
            .field("keep-ratio", self.keep_ratio)
            .field("inference-mean-us", self.inference_mean_us)
            .field("inference-p50-us", self.inference_p50_us)
            .field("inference-p99-us", self.inference_p99_us)
            .field("interval-frames-in", self.interval_frames_in)
            .field("interval-frames-kept", self.interval_frames_kept)
            .field("interval-frames-screened", self.interval_frames_screened)
            .field(
                "interval-inference-mean-us",
                self.interval_inference_mean_us,
            )
            .field("interval-inference-p50-us", self.interval_inference_p50_us)
            .field("interval-inference-p99-us", self.interval_inference_p99_us)
            .field("execution-provider", self.execution_provider.as_str())
            .field("model", self.model.as_str())
            .field("model-precision", self.model_precision.as_str())
            .field("threshold", self.threshold)
            .field("feedback-offset", self.feedback_offset)
            .field_if_some("server", self.server.as_ref().map(|v| v.server.as_str()))
            .field_if_some(
                "server-model",
                self.server.as_ref().map(|v| v.server_model.as_str()),
            )
            .field_if_some("server-requests", self.server.as_ref().map(|v| v.requests))
            .field_if_some(
                "server-failed-requests",
                self.server.as_ref().map(|v| v.failed_requests),
            )
            .field_if_some(
                "server-latency-p50-us",
                self.server.as_ref().map(|v| v.latency_p50_us),
            )
            .field_if_some(
                "server-latency-p99-us",
                self.server.as_ref().map(|v| v.latency_p99_us),
            )
            .build()
    }

    pub fn from_structure(s: &gst::StructureRef) -> Result<StatsMessage, StatsParseError> {
        if s.name() != STATS_MESSAGE {
            return Err(StatsParseError(format!("its name is {}", s.name())));
        }
        fn get<'a, T: gst::glib::value::FromValue<'a> + 'static>(
            s: &'a gst::StructureRef,
            f: &str,
        ) -> Result<T, StatsParseError> {
            s.get::<T>(f)
                .map_err(|e| StatsParseError(format!("{f}: {e}")))
        }
        Ok(StatsMessage {
            frames_in: get(s, "frames-in")?,
            frames_kept: get(s, "frames-kept")?,
            frames_screened: get(s, "frames-screened")?,
            // Absent from the messages of versions before it.
            frames_junk: s.get("frames-junk").unwrap_or(0),
            keep_ratio: get(s, "keep-ratio")?,
            inference_mean_us: get(s, "inference-mean-us")?,
            inference_p50_us: get(s, "inference-p50-us")?,
            inference_p99_us: get(s, "inference-p99-us")?,
            interval_frames_in: get(s, "interval-frames-in")?,
            interval_frames_kept: get(s, "interval-frames-kept")?,
            interval_frames_screened: get(s, "interval-frames-screened")?,
            interval_inference_mean_us: get(s, "interval-inference-mean-us")?,
            interval_inference_p50_us: get(s, "interval-inference-p50-us")?,
            interval_inference_p99_us: get(s, "interval-inference-p99-us")?,
            execution_provider: get(s, "execution-provider")?,
            model: get(s, "model")?,
            model_precision: get(s, "model-precision")?,
            threshold: get(s, "threshold")?,
            feedback_offset: get(s, "feedback-offset")?,
            server: if s.has_field("server") {
                Some(ServerStats {
                    server: get(s, "server")?,
                    server_model: get(s, "server-model")?,
                    requests: get(s, "server-requests")?,
                    failed_requests: get(s, "server-failed-requests")?,
                    latency_p50_us: get(s, "server-latency-p50-us")?,
                    latency_p99_us: get(s, "server-latency-p99-us")?,
                })
            } else {
                None
            },
        })
    }
}

impl From<&StatsMessage> for gst::Structure {
    fn from(m: &StatsMessage) -> gst::Structure {
        m.to_structure()
    }
}

impl TryFrom<&gst::StructureRef> for StatsMessage {
    type Error = StatsParseError;
    fn try_from(s: &gst::StructureRef) -> Result<StatsMessage, StatsParseError> {
        StatsMessage::from_structure(s)
    }
}

/// Sub-buckets per power of two: values are kept to within 1/`SUB` (about 3 %) of their size.
const SUB_BITS: u32 = 5;
const SUB: usize = 1 << SUB_BITS;
/// Buckets: values below `SUB` exactly, then `SUB` per octave up to `u64::MAX`.
const BUCKETS: usize = SUB * (64 - SUB_BITS as usize + 1);

/// A fixed-size log-bucket histogram of microsecond times (like HdrHistogram with 5 bits of
/// precision): constant memory (a few KiB) whatever the number of samples, O(1) to record, and
/// percentiles within about 3 % (reported as the bucket's upper bound, capped at the maximum seen).
#[derive(Clone)]
pub struct Histogram {
    counts: Box<[u64; BUCKETS]>,
    count: u64,
    sum: u128,
    max: u64,
}

impl std::fmt::Debug for Histogram {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("Histogram")
            .field("count", &self.count)
            .field("mean", &self.mean())
            .field("max", &self.max)
            .finish()
    }
}

impl Default for Histogram {
    fn default() -> Self {
        Histogram {
            counts: Box::new([0; BUCKETS]),
            count: 0,
            sum: 0,
            max: 0,
        }
    }
}

fn bucket_of(v: u64) -> usize {
    if v < SUB as u64 {
        return v as usize;
    }
    let msb = 63 - v.leading_zeros(); // >= SUB_BITS
    let shift = msb - SUB_BITS;
    let sub = ((v >> shift) as usize) - SUB; // 0..SUB
    SUB * (shift as usize + 1) + sub
}

/// The largest value that falls in bucket `b`.
fn bucket_high(b: usize) -> u64 {
    if b < SUB {
        return b as u64;
    }
    let shift = (b / SUB - 1) as u32;
    let sub = (b % SUB) as u64 + SUB as u64;
    let low = sub << shift;
    low.saturating_add((1u64 << shift) - 1)
}

impl Histogram {
    pub fn record(&mut self, v: u64) {
        self.counts[bucket_of(v)] += 1;
        self.count += 1;
        self.sum += v as u128;
        self.max = self.max.max(v);
    }

    #[cfg(test)]
    fn count(&self) -> u64 {
        self.count
    }

    pub fn clear(&mut self) {
        if self.count > 0 {
            self.counts.fill(0);
        }
        self.count = 0;
        self.sum = 0;
        self.max = 0;
    }

    /// Mean (0 with no sample).
    pub fn mean(&self) -> f64 {
        if self.count == 0 {
            0.0
        } else {
            self.sum as f64 / self.count as f64
        }
    }

    /// Nearest-rank percentile `p` in (0, 100] (0 with no sample), to within a bucket.
    pub fn percentile(&self, p: f64) -> u64 {
        if self.count == 0 {
            return 0;
        }
        let rank = ((p / 100.0) * self.count as f64).ceil().max(1.0) as u64;
        let rank = rank.min(self.count);
        let mut seen = 0u64;
        for (b, &c) in self.counts.iter().enumerate() {
            seen += c;
            if seen >= rank {
                return bucket_high(b).min(self.max);
            }
        }
        self.max
    }
}

/// Per-frame inference times, over the whole run and since the last stats message, in bounded
/// memory (two [`Histogram`]s).
#[derive(Debug, Clone, Default)]
pub struct InferenceStats {
    run: Histogram,
    interval: Histogram,
}

impl InferenceStats {
    pub fn record(&mut self, us: u64) {
        self.run.record(us);
        self.interval.record(us);
    }

    pub fn interval(&self) -> &Histogram {
        &self.interval
    }

    /// Start a new interval (after a stats message).
    pub fn start_interval(&mut self) {
        self.interval.clear();
    }

    #[cfg(test)]
    fn count(&self) -> u64 {
        self.run.count()
    }

    /// Mean over the run in microseconds (0 with no sample).
    pub fn mean_us(&self) -> f64 {
        self.run.mean()
    }

    /// Percentile `p` in (0, 100] over the run, microseconds (0 with no sample).
    pub fn percentile_us(&self, p: f64) -> u64 {
        self.run.percentile(p)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn mean_and_p99() {
        let mut s = InferenceStats::default();
        assert_eq!((s.mean_us(), s.percentile_us(99.0)), (0.0, 0));
        for us in 1..=200u64 {
            s.record(us);
        }
        assert_eq!(s.count(), 200);
        assert!((s.mean_us() - 100.5).abs() < 1e-9);
        // Within a bucket (1/32 of the value).
        let close = |got: u64, want: u64| got >= want && got <= want + want / 32;
        assert!(
            close(s.percentile_us(99.0), 198),
            "{}",
            s.percentile_us(99.0)
        );
        assert_eq!(s.percentile_us(100.0), 200);
        assert!(
            close(s.percentile_us(50.0), 100),
            "{}",
            s.percentile_us(50.0)
        );
        assert_eq!(s.interval().count(), 200);
        s.start_interval();
        assert_eq!(s.interval().count(), 0);
        assert_eq!(s.interval().percentile(50.0), 0);
        s.record(7);
        assert_eq!(s.interval().percentile(99.0), 7);
        assert_eq!(s.count(), 201);
    }

    #[test]
    fn histogram_is_bounded_and_accurate() {
        // Every bucket boundary maps back into its own bucket.
        for v in (0..5000u64).chain([u64::MAX, u64::MAX / 3, 1 << 40]) {
            let b = bucket_of(v);
            assert!(b < BUCKETS);
            assert!(bucket_high(b) >= v, "{v}");
            assert!(v >= bucket_high(b) - bucket_high(b) / 16, "{v}");
        }
        let mut h = Histogram::default();
        let size = std::mem::size_of_val(&*h.counts);
        for i in 0..1_000_000u64 {
            h.record(i % 10_000);
        }
        assert_eq!(
            std::mem::size_of_val(&*h.counts),
            size,
            "memory does not grow"
        );
        let p50 = h.percentile(50.0);
        assert!((4800..=5200).contains(&p50), "{p50}");
        let p99 = h.percentile(99.0);
        assert!((9700..=10_000).contains(&p99), "{p99}");
        assert!((h.mean() - 4999.5).abs() < 1e-6);
    }

    #[test]
    fn stats_message_round_trip_and_errors() {
        gst::init().unwrap();
        let m = StatsMessage {
            frames_in: 10,
            frames_kept: 3,
            frames_screened: 5,
            frames_junk: 3,
            keep_ratio: 0.3,
            inference_mean_us: 812.5,
            inference_p50_us: 800,
            inference_p99_us: 1400,
            interval_frames_in: 4,
            interval_frames_kept: 1,
            interval_frames_screened: 2,
            interval_inference_mean_us: 790.0,
            interval_inference_p50_us: 780,
            interval_inference_p99_us: 900,
            execution_provider: "cpu".into(),
            model: "leangate-s".into(),
            model_precision: "int8".into(),
            threshold: 0.5,
            feedback_offset: 0.05,
            server: None,
        };
        let s = m.to_structure();
        assert_eq!(s.name(), STATS_MESSAGE);
        assert_eq!(s.get::<u64>("frames-kept").unwrap(), 3);
        assert_eq!(s.get::<u64>("frames-screened").unwrap(), 5);
        assert_eq!(s.get::<f64>("feedback-offset").unwrap(), 0.05);
        assert_eq!(StatsMessage::from_structure(&s).unwrap(), m);
        let mut broken = s.clone();
        broken.remove_field("threshold");
        let e = StatsMessage::from_structure(&broken).unwrap_err();
        assert!(e.to_string().contains("threshold"), "{e}");
        let remote = StatsMessage {
            server: Some(ServerStats {
                server: "http://127.0.0.1:8000".into(),
                server_model: "leangate-s-encoder".into(),
                requests: 9,
                failed_requests: 2,
                latency_p50_us: 1500,
                latency_p99_us: 4000,
            }),
            ..m.clone()
        };
        let rs = remote.to_structure();
        assert_eq!(rs.get::<u64>("server-failed-requests").unwrap(), 2);
        assert_eq!(StatsMessage::from_structure(&rs).unwrap(), remote);
        assert!(!s.has_field("server-requests"));
        let other = gst::Structure::new_empty("something-else");
        assert!(StatsMessage::from_structure(&other).is_err());
    }
}

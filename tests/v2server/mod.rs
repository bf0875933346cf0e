//! A real KServe V2 server on loopback for the remote-scoring tests and benchmark: NVIDIA Triton
//! Inference Server through PyTriton (`scripts/v2_server.py`, in `.venv-triton` made by
//! `scripts/setup.sh`), serving the shipped student's ONNX files.
//!
//! The server runs in its own process group; dropping [`V2Server`] sends SIGTERM to the group,
//! waits (bounded), then SIGKILLs it, so no process outlives the test. The script also stops
//! by itself when its parent (the test) goes away.
#![allow(dead_code)]

/// A scripted V2 server for hostile behaviours (tests/v2server/scripted.rs).
pub mod scripted;

use std::net::TcpListener;
use std::os::unix::process::CommandExt;
use std::path::PathBuf;
use std::process::{Child, Command, Stdio};
use std::time::{Duration, Instant};

pub fn repo_root() -> PathBuf {
    PathBuf::from(env!("CARGO_MANIFEST_DIR"))
}

/// The venv's python, or None (with the reason) when PyTriton is not installed.
pub fn python() -> Result<PathBuf, String> {
    let py = repo_root().join(".venv-triton/bin/python");
    if !py.exists() {
        return Err(format!(
            "{} is absent: run scripts/setup.sh (it installs nvidia-pytriton into .venv-triton \
             from Debian's /usr/bin/python3)",
            py.display()
        ));
    }
    let ok = Command::new(&py)
        .args(["-c", "import pytriton, onnxruntime"])
        // This probe imports onnxruntime directly: no device id or usage events in HOME.
        .env("ORT_DISABLE_TELEMETRY", "1")
        .stdout(Stdio::null())
        .stderr(Stdio::null())
        .status()
        .map(|s| s.success())
        .unwrap_or(false);
    if ok {
        Ok(py)
    } else {
        Err(format!(
            "{} cannot import pytriton and onnxruntime: run scripts/setup.sh",
            py.display()
        ))
    }
}

/// A free TCP port on 127.0.0.1 (released at once; good enough for tests).
pub fn free_port() -> u16 {
    TcpListener::bind("127.0.0.1:0")
        .unwrap()
        .local_addr()
        .unwrap()
        .port()
}

/// The shipped student's files, served under their names.
pub fn student_models() -> Vec<String> {
    let m = repo_root().join("models");
    ["leangate-s-encoder", "leangate-s-head", "leangate-s"]
        .iter()
        .map(|n| format!("{n}={}", m.join(format!("{n}.onnx")).display()))
        .collect()
}

pub struct V2Server {
    child: Option<Child>,
    pub http_port: u16,
    grpc_port: u16,
    models: Vec<String>,
    pub dir: tempfile::TempDir,
}

impl V2Server {
    /// Start a server for `models` (`NAME=path.onnx`) and wait until every model is ready.
    pub fn start(models: &[String]) -> Result<V2Server, String> {
        let dir = tempfile::tempdir().map_err(|e| e.to_string())?;
        let mut s = V2Server {
            child: None,
            http_port: free_port(),
            grpc_port: free_port(),
            models: models.to_vec(),
            dir,
        };
        s.spawn()?;
        Ok(s)
    }

    pub fn url(&self) -> String {
        format!("http://127.0.0.1:{}", self.http_port)
    }

    pub fn log(&self) -> PathBuf {
        self.dir.path().join("server.log")
    }

    pub fn counts_path(&self) -> PathBuf {
        self.dir.path().join("counts.json")
    }

    pub fn delay_path(&self) -> PathBuf {
        self.dir.path().join("delay-ms")
    }

    /// Rows served per model since the server (re)started.
    pub fn count(&self, model: &str) -> u64 {
        std::fs::read_to_string(self.counts_path())
            .ok()
            .and_then(|t| serde_json::from_str::<serde_json::Value>(&t).ok())
            .and_then(|v| v.get(model).and_then(|n| n.as_u64()))
            .unwrap_or(0)
    }

    /// Make every inference call wait this long (0 = none).
    pub fn set_delay_ms(&self, ms: u64) {
        std::fs::write(self.delay_path(), ms.to_string()).unwrap();
    }

    /// (Re)start the server on the same ports.
    pub fn spawn(&mut self) -> Result<(), String> {
        let py = python()?;
        let log = std::fs::OpenOptions::new()
            .create(true)
            .append(true)
            .open(self.log())
            .map_err(|e| e.to_string())?;
        let _ = std::fs::remove_file(self.counts_path());
        // PyTriton creates its workspace; a killed server's is still there.
        let _ = std::fs::remove_dir_all(self.dir.path().join("workspace"));
        let child = Command::new(py)
            .arg(repo_root().join("scripts/v2_server.py"))
            .args(&self.models)
            .args(["--http-port", &self.http_port.to_string()])
            .args(["--grpc-port", &self.grpc_port.to_string()])
            .args(["--metrics-port", &free_port().to_string()])
            .arg("--counts")
            .arg(self.counts_path())
            .arg("--delay-file")
            .arg(self.delay_path())
            // Inside the temporary directory: nothing is left behind even after a SIGKILL.
            .arg("--workspace")
            .arg(self.dir.path().join("workspace"))
            .stdin(Stdio::null())
            .stdout(log.try_clone().map_err(|e| e.to_string())?)
            .stderr(log)
            .process_group(0)
            .spawn()
            .map_err(|e| format!("cannot start scripts/v2_server.py: {e}"))?;
        self.child = Some(child);
        self.wait_ready(Duration::from_secs(90))
    }

    fn wait_ready(&mut self, limit: Duration) -> Result<(), String> {
        let agent: ureq::Agent = ureq::Agent::config_builder()
            .timeout_global(Some(Duration::from_secs(2)))
            .http_status_as_error(false)
            .build()
            .into();
        let names: Vec<String> = self
            .models
            .iter()
            .map(|m| m.split('=').next().unwrap().to_string())
            .collect();
        let t0 = Instant::now();
        loop {
            let ready = names.iter().all(|n| {
                agent
                    .get(format!("{}/v2/models/{n}/ready", self.url()))
                    .call()
                    .map(|r| r.status().as_u16() == 200)
                    .unwrap_or(false)
            });
            if ready {
                return Ok(());
            }
            if let Some(c) = self.child.as_mut() {
                if let Ok(Some(status)) = c.try_wait() {
                    let log = std::fs::read_to_string(self.log()).unwrap_or_default();
                    self.child = None;
                    return Err(format!(
                        "the V2 server exited ({status}) before its models were ready; log:\n{}",
                        tail(&log, 3000)
                    ));
                }
            }
            if t0.elapsed() > limit {
                let log = std::fs::read_to_string(self.log()).unwrap_or_default();
                self.stop();
                return Err(format!(
                    "the V2 server was not ready in {limit:?}; log:\n{}",
                    tail(&log, 3000)
                ));
            }
            std::thread::sleep(Duration::from_millis(200));
        }
    }

    /// The process group id of the running server (its leader's pid).
    pub fn pgid(&self) -> Option<u32> {
        self.child.as_ref().map(|c| c.id())
    }

    /// Stop the server and everything it started: SIGTERM to the group, up to 15 s, SIGKILL.
    pub fn stop(&mut self) {
        let Some(mut child) = self.child.take() else {
            return;
        };
        let pgid = child.id();
        signal_group(pgid, "TERM");
        let t0 = Instant::now();
        while t0.elapsed() < Duration::from_secs(15) {
            if let Ok(Some(_)) = child.try_wait() {
                break;
            }
            std::thread::sleep(Duration::from_millis(100));
        }
        // The leader has exited (or is late): whatever is left of the group goes too.
        signal_group(pgid, "KILL");
        let _ = child.kill();
        let _ = child.wait();
        remove_shm(pgid);
    }

    /// Kill the server abruptly (SIGKILL to the whole group), as a crash would; then remove what
    /// a clean stop would have (its shared memory, the Python backend's folders in /tmp).
    pub fn kill(&mut self) {
        if let Some(mut child) = self.child.take() {
            let folders = backend_tmp_dirs(child.id());
            signal_group(child.id(), "KILL");
            let _ = child.wait();
            remove_shm(child.id());
            for f in folders {
                let _ = std::fs::remove_dir_all(f);
            }
        }
    }
}

/// Whether any process of group `pgid` is still running (zombies not counted), waiting up to
/// `within` for the group to go.
pub fn group_alive(pgid: u32, within: Duration) -> bool {
    let t0 = Instant::now();
    loop {
        if !group_members(pgid) {
            return false;
        }
        if t0.elapsed() >= within {
            return true;
        }
        std::thread::sleep(Duration::from_millis(50));
    }
}

/// Any live (non-zombie) process in group `pgid`.
fn group_members(pgid: u32) -> bool {
    !members(pgid).is_empty()
}

/// The /proc folders of the live (non-zombie) processes in group `pgid`, from /proc/<pid>/stat.
fn members(pgid: u32) -> Vec<PathBuf> {
    let Ok(dir) = std::fs::read_dir("/proc") else {
        return Vec::new();
    };
    dir.flatten()
        .map(|e| e.path())
        .filter(|p| {
            let Ok(stat) = std::fs::read_to_string(p.join("stat")) else {
                return false;
            };
            // pid (comm) state ppid pgrp ...: comm may hold spaces, so split after the last ')'.
            let Some(rest) = stat.rfind(')').map(|i| &stat[i + 1..]) else {
                return false;
            };
            let f: Vec<&str> = rest.split_whitespace().collect();
            f.len() > 2 && f[2] == pgid.to_string() && f[0] != "Z" && f[0] != "X"
        })
        .collect()
}

/// The folders Triton's Python backend makes in /tmp (its path is fixed there, whatever TMPDIR
/// says) for the server group `pgid`: the model folder its stub runs from
/// (`/tmp/folderXXXXXX/1/model.py` on the stub's command line) and the `python_env_XXXXXX`
/// folder made with it (the same instant, within 0.1 s). A clean stop removes both; a SIGKILL
/// leaves them.
pub fn backend_tmp_dirs(pgid: u32) -> Vec<PathBuf> {
    let tmp = std::path::Path::new("/tmp");
    let mut found = Vec::new();
    for p in members(pgid) {
        let Ok(cmd) = std::fs::read(p.join("cmdline")) else {
            continue;
        };
        for arg in cmd.split(|&b| b == 0) {
            let arg = String::from_utf8_lossy(arg);
            let Some(name) = arg.strip_prefix("/tmp/").and_then(|r| r.split('/').next()) else {
                continue;
            };
            let folder = tmp.join(name);
            if name.starts_with("folder") && folder.is_dir() && !found.contains(&folder) {
                found.push(folder);
            }
        }
    }
    let made = |p: &std::path::Path| {
        std::fs::metadata(p)
            .and_then(|m| m.created().or_else(|_| m.modified()))
            .ok()
    };
    let envs: Vec<PathBuf> = std::fs::read_dir(tmp)
        .into_iter()
        .flatten()
        .flatten()
        .map(|e| e.path())
        .filter(|p| {
            p.file_name()
                .is_some_and(|n| n.to_string_lossy().starts_with("python_env_"))
        })
        .collect();
    for folder in found.clone() {
        let Some(t) = made(&folder) else { continue };
        for env in &envs {
            let near = made(env).is_some_and(|e| {
                let d = if e > t {
                    e.duration_since(t)
                } else {
                    t.duration_since(e)
                };
                d.is_ok_and(|d| d < Duration::from_millis(100))
            });
            if near && !found.contains(env) {
                found.push(env.clone());
            }
        }
    }
    found
}

/// The Python backend's shared-memory regions of the server whose script ran as `pid` (a clean
/// stop removes them; a SIGKILL leaves them).
fn remove_shm(pid: u32) {
    let prefix = format!("pytrtion{pid}-");
    if let Ok(dir) = std::fs::read_dir("/dev/shm") {
        for e in dir.flatten() {
            if e.file_name().to_string_lossy().starts_with(&prefix) {
                let _ = std::fs::remove_file(e.path());
            }
        }
    }
}

fn signal_group(pgid: u32, sig: &str) {
    let _ = Command::new("kill")
        .args([&format!("-{sig}"), "--", &format!("-{pgid}")])
        .stderr(Stdio::null())
        .status();
}

fn tail(s: &str, n: usize) -> &str {
    let mut start = s.len().saturating_sub(n);
    while !s.is_char_boundary(start) {
        start += 1;
    }
    &s[start..]
}

impl Drop for V2Server {
    fn drop(&mut self) {
        self.stop();
    }
}

/// Start the student's server, or print why the test is skipped.
pub fn start_or_skip(models: &[String]) -> Option<V2Server> {
    if let Err(why) = python() {
        eprintln!("SKIPPED: no V2 server: {why}");
        return None;
    }
    match V2Server::start(models) {
        Ok(s) => Some(s),
        Err(e) => panic!("the V2 server is installed but did not start: {e}"),
    }
}

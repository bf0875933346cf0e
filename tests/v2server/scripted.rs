//! A scripted KServe V2 server on loopback: real HTTP/1.1 over TCP (keep-alive, one thread per
//! connection) that answers as the test's handler says. For the server behaviours Triton cannot
//! be made to show on demand: out-of-range utilities, impossible output shapes, redirects, an
//! error status on the model metadata, credentials checks, and counting how many inference
//! requests are in flight at once.

use std::io::{BufRead, BufReader, Read, Write};
use std::net::{SocketAddr, TcpListener, TcpStream};
use std::sync::atomic::{AtomicBool, AtomicU64, AtomicUsize, Ordering};
use std::sync::{Arc, Mutex};
use std::time::Duration;

use serde_json::{json, Value};

/// One request as the server read it.
#[derive(Debug, Clone)]
pub struct Request {
    pub method: String,
    pub path: String,
    /// Names lowercased.
    pub headers: Vec<(String, String)>,
    pub body: Vec<u8>,
}

impl Request {
    pub fn header(&self, name: &str) -> Option<&str> {
        let name = name.to_ascii_lowercase();
        self.headers
            .iter()
            .find(|(n, _)| *n == name)
            .map(|(_, v)| v.as_str())
    }

    pub fn is_infer(&self) -> bool {
        self.method == "POST" && self.path.ends_with("/infer")
    }
}

/// What the server answers.
#[derive(Debug, Clone)]
pub struct Reply {
    pub status: u16,
    pub headers: Vec<(String, String)>,
    pub body: Vec<u8>,
}

impl Reply {
    pub fn json(status: u16, v: &Value) -> Reply {
        Reply {
            status,
            headers: vec![("Content-Type".into(), "application/json".into())],
            body: serde_json::to_vec(v).unwrap(),
        }
    }

    pub fn redirect(status: u16, location: &str) -> Reply {
        Reply {
            status,
            headers: vec![("Location".into(), location.into())],
            body: Vec::new(),
        }
    }

    /// One FP32 output in the binary tensor extension, any shape (even one that does not fit
    /// the data).
    pub fn tensor(name: &str, shape: &[u64], data: &[f32]) -> Reply {
        let header = serde_json::to_vec(&json!({
            "model_name": "scripted",
            "outputs": [{
                "name": name,
                "datatype": "FP32",
                "shape": shape,
                "parameters": {"binary_data_size": data.len() * 4},
            }],
        }))
        .unwrap();
        let mut body = header.clone();
        for x in data {
            body.extend_from_slice(&x.to_le_bytes());
        }
        Reply {
            status: 200,
            headers: vec![
                ("Content-Type".into(), "application/octet-stream".into()),
                (
                    "Inference-Header-Content-Length".into(),
                    header.len().to_string(),
                ),
            ],
            body,
        }
    }
}

/// The model a scripted server pretends to serve, after a fixture of tests/fixtures: its
/// metadata, readiness and well-formed answers.
#[derive(Debug, Clone)]
pub enum Served {
    /// A pair model (`mad.onnx`: 64x64): `reference`, `current` -> `utility` [N].
    Pair { name: String, size: i64 },
    /// An encoder (`split_encoder.onnx`: 64x64 -> features [N,3,16,16]).
    Encoder {
        name: String,
        size: i64,
        features: Vec<i64>,
    },
}

impl Served {
    /// `mad.onnx`, served under its `leangate.name`.
    pub fn mad() -> Served {
        Served::Pair {
            name: "fixture-mad".into(),
            size: 64,
        }
    }

    /// `split_encoder.onnx`, served under `<leangate.name>-encoder`.
    pub fn split_encoder() -> Served {
        Served::Encoder {
            name: "fixture-split-encoder".into(),
            size: 64,
            features: vec![3, 16, 16],
        }
    }

    pub fn name(&self) -> &str {
        match self {
            Served::Pair { name, .. } | Served::Encoder { name, .. } => name,
        }
    }

    pub fn metadata(&self) -> Value {
        let t =
            |name: &str, shape: Vec<i64>| json!({"name": name, "datatype": "FP32", "shape": shape});
        match self {
            Served::Pair { name, size } => json!({
                "name": name,
                "platform": "scripted",
                "inputs": [t("reference", vec![-1, 3, *size, *size]), t("current", vec![-1, 3, *size, *size])],
                "outputs": [t("utility", vec![-1])],
            }),
            Served::Encoder {
                name,
                size,
                features,
            } => json!({
                "name": name,
                "platform": "scripted",
                "inputs": [t("image", vec![-1, 3, *size, *size])],
                "outputs": [t("features", [&[-1][..], features].concat())],
            }),
        }
    }

    /// A well-formed inference answer: `utility` (pair) or zero features (encoder).
    pub fn answer(&self, utility: f32) -> Reply {
        match self {
            Served::Pair { .. } => Reply::tensor("utility", &[1], &[utility]),
            Served::Encoder { features, .. } => {
                let shape: Vec<u64> = [&[1][..], features]
                    .concat()
                    .iter()
                    .map(|&d| d as u64)
                    .collect();
                let n = shape.iter().product::<u64>() as usize;
                Reply::tensor("features", &shape, &vec![0.0; n])
            }
        }
    }

    /// The V2 endpoints of this model: metadata, ready, and `infer` answered by `infer`; 404
    /// for anything else.
    pub fn route(&self, req: &Request, infer: impl FnOnce() -> Reply) -> Reply {
        let base = format!("/v2/models/{}", self.name());
        match (req.method.as_str(), req.path.strip_prefix(&base)) {
            ("GET", Some("")) => Reply::json(200, &self.metadata()),
            ("GET", Some("/ready")) => Reply::json(200, &json!({})),
            ("POST", Some("/infer")) => infer(),
            _ => Reply::json(
                404,
                &json!({"error": format!("no {} {}", req.method, req.path)}),
            ),
        }
    }
}

type Handler = dyn Fn(&Request, u64) -> Reply + Send + Sync;

#[derive(Default)]
struct Shared {
    infers: AtomicU64,
    in_flight: AtomicUsize,
    max_in_flight: AtomicUsize,
    seen: Mutex<Vec<Request>>,
    stop: AtomicBool,
}

/// The running server; dropping it stops accepting.
pub struct Scripted {
    addr: SocketAddr,
    shared: Arc<Shared>,
}

impl Scripted {
    /// Serve on a free port of 127.0.0.1. `handler(request, n)` answers every request; `n` is
    /// the number of inference requests (`POST .../infer`) before this one.
    pub fn start(handler: impl Fn(&Request, u64) -> Reply + Send + Sync + 'static) -> Scripted {
        let listener = TcpListener::bind("127.0.0.1:0").unwrap();
        let addr = listener.local_addr().unwrap();
        let shared = Arc::new(Shared::default());
        let handler: Arc<Handler> = Arc::new(handler);
        let s = shared.clone();
        std::thread::spawn(move || {
            for conn in listener.incoming() {
                if s.stop.load(Ordering::SeqCst) {
                    break;
                }
                let Ok(conn) = conn else { continue };
                let (s, handler) = (s.clone(), handler.clone());
                std::thread::spawn(move || serve(conn, &s, &*handler));
            }
        });
        Scripted { addr, shared }
    }

    pub fn port(&self) -> u16 {
        self.addr.port()
    }

    pub fn url(&self) -> String {
        format!("http://127.0.0.1:{}", self.port())
    }

    /// Inference requests answered or being answered.
    pub fn infers(&self) -> u64 {
        self.shared.infers.load(Ordering::SeqCst)
    }

    /// The most inference requests that were in the handler at once.
    pub fn max_in_flight(&self) -> usize {
        self.shared.max_in_flight.load(Ordering::SeqCst)
    }

    /// Count the most in flight from now on.
    pub fn reset_max_in_flight(&self) {
        let now = self.shared.in_flight.load(Ordering::SeqCst);
        self.shared.max_in_flight.store(now, Ordering::SeqCst);
    }

    /// Every request read so far (bodies included).
    pub fn seen(&self) -> Vec<Request> {
        self.shared.seen.lock().unwrap().clone()
    }
}

impl Drop for Scripted {
    fn drop(&mut self) {
        self.shared.stop.store(true, Ordering::SeqCst);
        // Wake the accept loop.
        let _ = TcpStream::connect(self.addr);
    }
}

fn serve(conn: TcpStream, s: &Shared, handler: &Handler) {
    let _ = conn.set_nodelay(true);
    let _ = conn.set_read_timeout(Some(Duration::from_secs(2)));
    let mut writer = conn.try_clone().unwrap();
    let mut reader = BufReader::new(conn);
    loop {
        let req = match read_request(&mut reader) {
            Ok(Some(r)) => r,
            Ok(None) => return,
            Err(_) if !s.stop.load(Ordering::SeqCst) => continue,
            Err(_) => return,
        };
        s.seen.lock().unwrap().push(req.clone());
        let reply = if req.is_infer() {
            let n = s.infers.fetch_add(1, Ordering::SeqCst);
            let now = s.in_flight.fetch_add(1, Ordering::SeqCst) + 1;
            s.max_in_flight.fetch_max(now, Ordering::SeqCst);
            let r = handler(&req, n);
            s.in_flight.fetch_sub(1, Ordering::SeqCst);
            r
        } else {
            handler(&req, s.infers.load(Ordering::SeqCst))
        };
        let mut head = format!("HTTP/1.1 {} Scripted\r\n", reply.status);
        for (k, v) in &reply.headers {
            head.push_str(&format!("{k}: {v}\r\n"));
        }
        head.push_str(&format!("Content-Length: {}\r\n\r\n", reply.body.len()));
        if writer.write_all(head.as_bytes()).is_err() || writer.write_all(&reply.body).is_err() {
            return;
        }
    }
}

/// One request, or None at the end of the connection. A read timeout between requests is an
/// error the caller retries (the client keeps the connection alive).
fn read_request(r: &mut BufReader<TcpStream>) -> std::io::Result<Option<Request>> {
    let mut line = String::new();
    if r.read_line(&mut line)? == 0 {
        return Ok(None);
    }
    let mut parts = line.split_whitespace();
    let (Some(method), Some(path)) = (parts.next(), parts.next()) else {
        return Ok(None);
    };
    let (method, path) = (method.to_string(), path.to_string());
    let mut headers = Vec::new();
    loop {
        let mut h = String::new();
        if r.read_line(&mut h)? == 0 {
            return Ok(None);
        }
        let h = h.trim_end();
        if h.is_empty() {
            break;
        }
        if let Some((k, v)) = h.split_once(':') {
            headers.push((k.trim().to_ascii_lowercase(), v.trim().to_string()));
        }
    }
    let len = headers
        .iter()
        .find(|(k, _)| k == "content-length")
        .and_then(|(_, v)| v.parse::<usize>().ok())
        .unwrap_or(0);
    let mut body = vec![0; len];
    r.read_exact(&mut body)?;
    Ok(Some(Request {
        method,
        path,
        headers,
        body,
    }))
}

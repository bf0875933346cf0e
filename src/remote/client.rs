//! A blocking KServe V2 / Open Inference Protocol client over HTTP(S) (`ureq`, rustls for
//! https), with the binary tensor data extension for requests and responses.
//!
//! Endpoints used: `GET /v2/models/{name}` (model metadata: the tensor contract),
//! `GET /v2/models/{name}/ready`, `POST /v2/models/{name}/infer`. Tensors travel as raw
//! little-endian float32 after the JSON header (`Inference-Header-Content-Length`); a response
//! without binary data (`"data": [...]` in the JSON) is read too.

use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::{Arc, Mutex};
use std::time::Duration;

use serde_json::{json, Value};

use super::url::{display_url, ServerUrl};

/// Header carrying the length of the JSON part of a binary-extension body.
const HEADER_LEN: &str = "Inference-Header-Content-Length";
/// Largest response body accepted (the JSON header and the output tensors).
const MAX_RESPONSE_BYTES: u64 = 256 << 20;

/// What went wrong with one HTTP exchange.
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum ClientError {
    /// No answer: connection refused, DNS, TLS, timeout, broken connection.
    Transport(String),
    /// The server answered with an HTTP error status (and its `error` text, when it gave one).
    Status { code: u16, message: String },
    /// The server answered with a redirect (3xx), which is never followed: a POST must not
    /// turn into a GET elsewhere. `location` is shown with its userinfo hidden.
    Redirect { code: u16, location: String },
    /// The server answered something that is not a valid V2 response.
    Protocol(String),
    /// No (whole) answer within the request's time limit (`server-timeout`).
    Timeout(Duration),
}

impl std::fmt::Display for ClientError {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            ClientError::Transport(e) => write!(f, "{e}"),
            ClientError::Timeout(t) => {
                write!(f, "no answer within {} ms (server-timeout)", t.as_millis())
            }
            ClientError::Status { code, message } => {
                write!(f, "HTTP status {}", status_text(*code))?;
                if !message.is_empty() {
                    write!(f, ": {message}")?;
                }
                Ok(())
            }
            ClientError::Redirect { code, location } => write!(
                f,
                "HTTP status {}, a redirect to `{location}`, not followed (set `server` to \
                 the server's own address)",
                status_text(*code)
            ),
            ClientError::Protocol(e) => write!(f, "an invalid V2 response: {e}"),
        }
    }
}

/// One tensor of a model's metadata (`shape` uses -1 for a variable dimension).
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct TensorMeta {
    pub name: String,
    pub datatype: String,
    pub shape: Vec<i64>,
}

/// `GET /v2/models/{name}`.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct ModelMetadata {
    pub name: String,
    pub platform: String,
    pub inputs: Vec<TensorMeta>,
    pub outputs: Vec<TensorMeta>,
}

/// A float32 tensor going to the server.
#[derive(Debug, Clone, Copy)]
pub struct InputTensor<'a> {
    pub name: &'a str,
    pub shape: &'a [usize],
    pub data: &'a [f32],
}

/// A float32 tensor coming back.
#[derive(Debug, Clone, PartialEq)]
pub struct OutputTensor {
    pub name: String,
    pub shape: Vec<usize>,
    pub data: Vec<f32>,
}

/// `404 (Not Found)`, or the bare code when it has no standard reason.
fn status_text(code: u16) -> String {
    match ureq::http::StatusCode::from_u16(code)
        .ok()
        .and_then(|s| s.canonical_reason())
    {
        Some(reason) => format!("{code} ({reason})"),
        None => code.to_string(),
    }
}

/// A V2 HTTP client for one server (`http://host:port` or `https://host:port`, optionally with
/// a path prefix). Keeps its connections alive between requests. The URL's userinfo, if any,
/// goes in an `Authorization: Basic` header, never in the request's URI (so no transport
/// error can show it). Redirects are not followed. Clones share their connections and their
/// [`Canceller`].
#[derive(Clone)]
pub struct V2Client {
    agent: Canceller,
    base: String,
    authorization: Option<String>,
    timeout: Duration,
}

impl std::fmt::Debug for V2Client {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("V2Client")
            .field("base", &self.base)
            .finish()
    }
}

/// Interrupts a [`V2Client`]'s requests from another thread (a pipeline stopping or flushing):
/// [`Canceller::cancel`] closes its connections, so that a request waiting for the server fails
/// at once instead of at its timeout, and the requests that follow fail at once too, until
/// [`Canceller::resume`]. (A TCP connect in progress is not interrupted: it is bounded by the
/// timeout.)
#[derive(Clone)]
pub struct Canceller(Arc<Slot>);

struct Slot {
    config: ureq::config::Config,
    agent: Mutex<ureq::Agent>,
    cancelled: AtomicBool,
}

impl std::fmt::Debug for Canceller {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("Canceller")
            .field("cancelled", &self.is_cancelled())
            .finish()
    }
}

impl Canceller {
    fn new(config: ureq::config::Config) -> Canceller {
        Canceller(Arc::new(Slot {
            agent: Mutex::new(config.clone().into()),
            config,
            cancelled: AtomicBool::new(false),
        }))
    }

    fn agent(&self) -> ureq::Agent {
        self.0
            .agent
            .lock()
            .unwrap_or_else(|e| e.into_inner())
            .clone()
    }

    /// Fail the requests in flight and those that follow, until [`Canceller::resume`].
    pub fn cancel(&self) {
        self.0.cancelled.store(true, Ordering::SeqCst);
        self.agent().shutdown();
    }

    /// Requests may go again (on new connections).
    pub fn resume(&self) {
        let mut agent = self.0.agent.lock().unwrap_or_else(|e| e.into_inner());
        if self.0.cancelled.swap(false, Ordering::SeqCst) {
            *agent = self.0.config.clone().into();
        }
    }

    /// Between [`Canceller::cancel`] and [`Canceller::resume`].
    pub fn is_cancelled(&self) -> bool {
        self.0.cancelled.load(Ordering::SeqCst)
    }
}

/// A ureq failure as a client error: a timeout says how long was waited, an answer over the size
/// limit is the server's answer (not "no answer").
fn transport(e: ureq::Error, timeout: Duration) -> ClientError {
    match e {
        ureq::Error::Timeout(_) => ClientError::Timeout(timeout),
        ureq::Error::BodyExceedsLimit(n) => {
            ClientError::Protocol(format!("an answer larger than the {n} bytes allowed"))
        }
        e => ClientError::Transport(e.to_string()),
    }
}

/// The most bytes of JSON an inference answer may carry: utilities and features as JSON numbers
/// take far less (8 MiB is a million values); parsed, JSON takes about 16 times its size, so a
/// hostile 256 MiB answer of `0,0,...` would take gigabytes. Tensors that large come as binary
/// data.
pub(crate) const MAX_JSON_BYTES: usize = 8 << 20;

impl V2Client {
    /// `timeout` bounds each whole request (connect, send, wait, receive).
    pub fn new(server: &ServerUrl, timeout: Duration) -> V2Client {
        let config = ureq::Agent::config_builder()
            .timeout_global(Some(timeout))
            .timeout_connect(Some(timeout))
            .http_status_as_error(false)
            .max_redirects(0)
            .no_delay(true)
            .max_idle_connections_per_host(4)
            .user_agent(concat!("leangate/", env!("CARGO_PKG_VERSION")))
            .build();
        V2Client {
            agent: Canceller::new(config),
            base: server.base(),
            authorization: server.authorization(),
            timeout,
        }
    }

    /// The handle that interrupts this client's requests (see [`Canceller`]).
    pub fn canceller(&self) -> Canceller {
        self.agent.clone()
    }

    fn get(&self, url: &str) -> Result<ureq::http::Response<ureq::Body>, ClientError> {
        let mut req = self.agent.agent().get(url);
        if let Some(a) = &self.authorization {
            req = req.header("Authorization", a);
        }
        let resp = req.call().map_err(|e| transport(e, self.timeout))?;
        refuse_redirect(resp)
    }

    fn model_url(&self, model: &str, tail: &str) -> String {
        format!("{}/v2/models/{}{}", self.base, model, tail)
    }

    fn get_json(&self, url: &str) -> Result<Value, ClientError> {
        let mut resp = self.get(url)?;
        let status = resp.status().as_u16();
        let body = resp
            .body_mut()
            .with_config()
            .limit(16 << 20)
            .read_to_vec()
            .map_err(|e| transport(e, self.timeout))?;
        if status >= 400 {
            return Err(status_error(status, &body));
        }
        serde_json::from_slice(&body).map_err(|e| ClientError::Protocol(e.to_string()))
    }

    /// `GET /v2/models/{name}/ready`: Ok(true) when ready, Ok(false) for any other status.
    pub fn model_ready(&self, model: &str) -> Result<bool, ClientError> {
        let resp = self.get(&self.model_url(model, "/ready"))?;
        Ok(resp.status().as_u16() == 200)
    }

    /// `GET /v2/models/{name}`.
    pub fn model_metadata(&self, model: &str) -> Result<ModelMetadata, ClientError> {
        let v = self.get_json(&self.model_url(model, ""))?;
        parse_metadata(&v)
    }

    /// `GET /v2/models/{name}/stats` (Triton's statistics extension), raw JSON.
    pub fn model_stats(&self, model: &str) -> Result<Value, ClientError> {
        self.get_json(&self.model_url(model, "/stats"))
    }

    /// `POST /v2/models/{name}/infer` with binary tensors; returns the requested outputs, in
    /// the order asked for.
    pub fn infer(
        &self,
        model: &str,
        inputs: &[InputTensor<'_>],
        outputs: &[&str],
    ) -> Result<Vec<OutputTensor>, ClientError> {
        let (body, json_len) = encode_request(inputs, outputs)?;
        let mut req = self
            .agent
            .agent()
            .post(&self.model_url(model, "/infer"))
            .header("Content-Type", "application/octet-stream")
            .header(HEADER_LEN, json_len.to_string());
        if let Some(a) = &self.authorization {
            req = req.header("Authorization", a);
        }
        let resp = req
            .send(&body[..])
            .map_err(|e| transport(e, self.timeout))?;
        let mut resp = refuse_redirect(resp)?;
        let status = resp.status().as_u16();
        let header_len = resp
            .headers()
            .get(HEADER_LEN)
            .and_then(|v| v.to_str().ok())
            .map(|v| v.trim().parse::<usize>())
            .transpose()
            .map_err(|e| ClientError::Protocol(format!("bad {HEADER_LEN}: {e}")))?;
        let body = resp
            .body_mut()
            .with_config()
            .limit(MAX_RESPONSE_BYTES)
            .read_to_vec()
            .map_err(|e| transport(e, self.timeout))?;
        if status >= 400 {
            return Err(status_error(status, &body));
        }
        decode_response(&body, header_len, outputs)
    }
}

/// A 3xx answer as an error naming the status and where it points.
fn refuse_redirect(
    resp: ureq::http::Response<ureq::Body>,
) -> Result<ureq::http::Response<ureq::Body>, ClientError> {
    let code = resp.status().as_u16();
    if !(300..400).contains(&code) {
        return Ok(resp);
    }
    let location = resp
        .headers()
        .get("location")
        .map(|l| display_url(&String::from_utf8_lossy(l.as_bytes())))
        .unwrap_or_else(|| "(no Location)".into());
    Err(ClientError::Redirect { code, location })
}

fn status_error(code: u16, body: &[u8]) -> ClientError {
    let message = serde_json::from_slice::<Value>(body)
        .ok()
        .and_then(|v| v.get("error").and_then(Value::as_str).map(str::to_string))
        .unwrap_or_else(|| {
            String::from_utf8_lossy(&body[..body.len().min(300)])
                .trim()
                .to_string()
        });
    ClientError::Status { code, message }
}

fn parse_tensors(v: &Value, key: &str) -> Result<Vec<TensorMeta>, ClientError> {
    let Some(list) = v.get(key) else {
        return Ok(Vec::new());
    };
    let list = list
        .as_array()
        .ok_or_else(|| ClientError::Protocol(format!("`{key}` is not a list")))?;
    list.iter()
        .map(|t| {
            let name = t.get("name").and_then(Value::as_str);
            let datatype = t.get("datatype").and_then(Value::as_str);
            let shape = t
                .get("shape")
                .and_then(Value::as_array)
                .and_then(|s| s.iter().map(Value::as_i64).collect::<Option<Vec<i64>>>());
            match (name, datatype, shape) {
                (Some(n), Some(d), Some(s)) => Ok(TensorMeta {
                    name: n.to_string(),
                    datatype: d.to_string(),
                    shape: s,
                }),
                _ => Err(ClientError::Protocol(format!(
                    "a tensor in `{key}` lacks name, datatype or shape: {t}"
                ))),
            }
        })
        .collect()
}

pub(crate) fn parse_metadata(v: &Value) -> Result<ModelMetadata, ClientError> {
    Ok(ModelMetadata {
        name: v
            .get("name")
            .and_then(Value::as_str)
            .unwrap_or_default()
            .to_string(),
        platform: v
            .get("platform")
            .and_then(Value::as_str)
            .unwrap_or_default()
            .to_string(),
        inputs: parse_tensors(v, "inputs")?,
        outputs: parse_tensors(v, "outputs")?,
    })
}

/// The request body (JSON header, then each input's bytes) and the header's length.
pub(crate) fn encode_request(
    inputs: &[InputTensor<'_>],
    outputs: &[&str],
) -> Result<(Vec<u8>, usize), ClientError> {
    let header = json!({
        "inputs": inputs.iter().map(|t| json!({
            "name": t.name,
            "shape": t.shape,
            "datatype": "FP32",
            "parameters": {"binary_data_size": t.data.len() * 4},
        })).collect::<Vec<_>>(),
        "outputs": outputs.iter().map(|name| json!({
            "name": name,
            "parameters": {"binary_data": true},
        })).collect::<Vec<_>>(),
    });
    let header = serde_json::to_vec(&header).map_err(|e| ClientError::Protocol(e.to_string()))?;
    let data: usize = inputs.iter().map(|t| t.data.len() * 4).sum();
    let mut body = Vec::new();
    body.try_reserve_exact(header.len() + data).map_err(|e| {
        ClientError::Transport(format!("cannot allocate a {} byte request: {e}", data))
    })?;
    body.extend_from_slice(&header);
    for t in inputs {
        for x in t.data {
            body.extend_from_slice(&x.to_le_bytes());
        }
    }
    Ok((body, header.len()))
}

/// Split a response into its JSON header and binary part, and pick out the outputs.
pub(crate) fn decode_response(
    body: &[u8],
    header_len: Option<usize>,
    wanted: &[&str],
) -> Result<Vec<OutputTensor>, ClientError> {
    let json_len = header_len.unwrap_or(body.len());
    if json_len > MAX_JSON_BYTES {
        return Err(ClientError::Protocol(format!(
            "a JSON answer of {json_len} bytes, more than the {MAX_JSON_BYTES} allowed (send large \
             tensors as binary data)"
        )));
    }
    if json_len > body.len() {
        return Err(ClientError::Protocol(format!(
            "{HEADER_LEN} {json_len} exceeds the body ({} bytes)",
            body.len()
        )));
    }
    let header: Value = serde_json::from_slice(&body[..json_len])
        .map_err(|e| ClientError::Protocol(format!("JSON header: {e}")))?;
    let list = header
        .get("outputs")
        .and_then(Value::as_array)
        .ok_or_else(|| ClientError::Protocol("no `outputs` list".into()))?;
    let mut binary = &body[json_len..];
    let mut got = Vec::with_capacity(list.len());
    for out in list {
        let name = out
            .get("name")
            .and_then(Value::as_str)
            .ok_or_else(|| ClientError::Protocol("an output without a name".into()))?;
        let datatype = out.get("datatype").and_then(Value::as_str).unwrap_or("");
        let shape: Vec<usize> = out
            .get("shape")
            .and_then(Value::as_array)
            .and_then(|s| s.iter().map(|d| d.as_u64().map(|d| d as usize)).collect())
            .ok_or_else(|| ClientError::Protocol(format!("output `{name}` has no shape")))?;
        let size = out
            .get("parameters")
            .and_then(|p| p.get("binary_data_size"))
            .and_then(Value::as_u64);
        let data = match size {
            Some(size) => {
                let size = size as usize;
                if size > binary.len() {
                    return Err(ClientError::Protocol(format!(
                        "output `{name}` announces {size} bytes, {} left",
                        binary.len()
                    )));
                }
                let (mine, rest) = binary.split_at(size);
                binary = rest;
                if datatype != "FP32" {
                    return Err(ClientError::Protocol(format!(
                        "output `{name}` is {datatype}, expected FP32"
                    )));
                }
                if !size.is_multiple_of(4) {
                    return Err(ClientError::Protocol(format!(
                        "output `{name}`: {size} bytes is not a whole number of FP32"
                    )));
                }
                mine.chunks_exact(4)
                    .map(|b| f32::from_le_bytes([b[0], b[1], b[2], b[3]]))
                    .collect()
            }
            None => out
                .get("data")
                .and_then(Value::as_array)
                .and_then(|d| {
                    d.iter()
                        .map(|x| x.as_f64().map(|x| x as f32))
                        .collect::<Option<Vec<f32>>>()
                })
                .ok_or_else(|| {
                    ClientError::Protocol(format!("output `{name}` has neither binary nor data"))
                })?,
        };
        let n = shape
            .iter()
            .try_fold(1usize, |n, &d| n.checked_mul(d))
            .ok_or_else(|| {
                ClientError::Protocol(format!("output `{name}` has an impossible shape {shape:?}"))
            })?;
        if n != data.len() {
            return Err(ClientError::Protocol(format!(
                "output `{name}` has shape {shape:?} but {} values",
                data.len()
            )));
        }
        got.push(OutputTensor {
            name: name.to_string(),
            shape,
            data,
        });
    }
    wanted
        .iter()
        .map(|w| {
            let i = got
                .iter()
                .position(|o| o.name == *w)
                .ok_or_else(|| ClientError::Protocol(format!("no output `{w}` in the response")))?;
            Ok(got.swap_remove(i))
        })
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn request_layout() {
        let a = [1.0f32, 2.0];
        let (body, n) = encode_request(
            &[InputTensor {
                name: "image",
                shape: &[1, 2],
                data: &a,
            }],
            &["features"],
        )
        .unwrap();
        let h: Value = serde_json::from_slice(&body[..n]).unwrap();
        assert_eq!(h["inputs"][0]["parameters"]["binary_data_size"], 8);
        assert_eq!(h["outputs"][0]["parameters"]["binary_data"], true);
        assert_eq!(&body[n..n + 4], &1.0f32.to_le_bytes());
        assert_eq!(body.len(), n + 8);
    }

    #[test]
    fn response_binary_and_json() {
        let header = br#"{"model_name":"m","outputs":[{"name":"a","datatype":"FP32","shape":[1],"parameters":{"binary_data_size":4}},{"name":"b","datatype":"FP32","shape":[2],"data":[0.5,1.5]}]}"#;
        let mut body = header.to_vec();
        body.extend_from_slice(&0.25f32.to_le_bytes());
        let got = decode_response(&body, Some(header.len()), &["b", "a"]).unwrap();
        assert_eq!(got[0].data, vec![0.5, 1.5]);
        assert_eq!(got[1].data, vec![0.25]);
        assert!(decode_response(&body, Some(header.len()), &["c"]).is_err());
        assert!(decode_response(&body[..body.len() - 1], Some(header.len()), &["a"]).is_err());
    }

    #[test]
    fn impossible_shape_is_a_protocol_error() {
        let header = br#"{"outputs":[{"name":"f","datatype":"FP32","shape":[4294967296,4294967296,1],"data":[]}]}"#;
        let e = decode_response(header, None, &["f"]).unwrap_err();
        assert!(e.to_string().contains("impossible shape"), "{e}");
    }

    #[test]
    fn metadata() {
        let v: Value = serde_json::from_str(
            r#"{"name":"m","versions":["1"],"platform":"onnxruntime_onnx","inputs":[{"name":"image","datatype":"FP32","shape":[-1,3,256,256]}],"outputs":[{"name":"features","datatype":"FP32","shape":[-1,64,8,8]}]}"#,
        )
        .unwrap();
        let m = parse_metadata(&v).unwrap();
        assert_eq!(m.inputs[0].shape, vec![-1, 3, 256, 256]);
        assert_eq!(m.outputs[0].name, "features");
    }
}

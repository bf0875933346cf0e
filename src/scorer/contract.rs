//! The model contract: input/output names, types and shapes, the `leangate.*` metadata, the
//! bounds on the input size, and where a split model's head may live.

use std::path::{Component, Path, PathBuf};

use ort::session::Session;
use ort::value::{TensorElementType, ValueType};

use super::{ModelInfo, ScorerError};
use crate::preprocess::{ResizeMode, TensorSpec};

/// Input size used when neither the metadata nor the graph fixes one.
pub const DEFAULT_INPUT_SIZE: (u32, u32) = (256, 256);
/// Largest accepted model input side, pixels.
pub const MAX_INPUT_SIDE: u32 = 4096;
/// Largest accepted input tensor (`3 x H x W` float32), bytes.
pub const MAX_TENSOR_BYTES: u64 = 64 << 20;
/// Smallest accepted `|leangate.std|` (a tiny std turns every frame into Inf/NaN).
pub const MIN_STD: f32 = 1e-6;

pub const CONTRACT: &str = "a LeanGate model is a pair model (float32 inputs `reference` and \
`current` of shape [N,3,H,W], N = 1 or dynamic, and a float32 output `utility` of shape [N] or \
[N,1]) or a split model (an encoder `image` → `features` and a head `reference_features`, \
`current_features` → `utility`); models/README.md, installed as \
share/doc/leangate/models/README.md";

pub(super) fn parse_triplet(s: &str) -> Option<[f32; 3]> {
    let v: Vec<f32> = s
        .split(|c: char| c == ',' || c.is_whitespace())
        .filter(|t| !t.is_empty())
        .map(|t| t.parse::<f32>().ok())
        .collect::<Option<_>>()?;
    (v.len() == 3).then(|| [v[0], v[1], v[2]])
}

/// Parse `WxH`.
pub fn parse_size(s: &str) -> Option<(u32, u32)> {
    let (w, h) = s.trim().split_once(['x', 'X'])?;
    let (w, h) = (w.trim().parse().ok()?, h.trim().parse().ok()?);
    (w > 0 && h > 0).then_some((w, h))
}

/// Refuse input sizes whose tensors would not fit (or would exhaust memory).
pub(super) fn check_input_size(w: u32, h: u32, model: &str) -> Result<(), ScorerError> {
    let bytes = 3 * 4 * w as u64 * h as u64;
    if w > MAX_INPUT_SIDE || h > MAX_INPUT_SIDE || bytes > MAX_TENSOR_BYTES {
        return Err(ScorerError::Metadata {
            model: model.to_string(),
            reason: format!(
                "input size {w}x{h} is too large (each side at most {MAX_INPUT_SIDE}, a tensor \
                 at most {} MiB; this one needs {} MiB)",
                MAX_TENSOR_BYTES >> 20,
                bytes >> 20
            ),
        });
    }
    Ok(())
}

fn tensor_dims(vt: &ValueType) -> Option<(TensorElementType, Vec<i64>)> {
    match vt {
        ValueType::Tensor { ty, shape, .. } => Some((*ty, shape.iter().copied().collect())),
        _ => None,
    }
}

fn contract(model: &str, reason: String) -> ScorerError {
    ScorerError::Contract {
        model: model.to_string(),
        reason,
    }
}

/// The dimensions of the float32 tensor `want` among a graph's inputs or outputs (`what`).
fn float32_dims<'a>(
    what: &str,
    outlets: impl Iterator<Item = (&'a str, &'a ValueType)>,
    want: &str,
    model: &str,
) -> Result<Vec<i64>, ScorerError> {
    let outlets: Vec<(&str, &ValueType)> = outlets.collect();
    let names: Vec<&str> = outlets.iter().map(|(n, _)| *n).collect();
    let (_, dtype) = outlets
        .iter()
        .find(|(n, _)| *n == want)
        .ok_or_else(|| contract(model, format!("it has {what}s {names:?}, no `{want}`")))?;
    let (ty, dims) = tensor_dims(dtype)
        .ok_or_else(|| contract(model, format!("{what} `{want}` is not a tensor")))?;
    if ty != TensorElementType::Float32 {
        return Err(contract(
            model,
            format!("{what} `{want}` is {ty:?}, not float32"),
        ));
    }
    Ok(dims)
}

fn input_dims(
    session: &Session,
    want: &str,
    rank4: bool,
    model: &str,
) -> Result<Vec<i64>, ScorerError> {
    let dims = float32_dims(
        "input",
        session.inputs().iter().map(|i| (i.name(), i.dtype())),
        want,
        model,
    )?;
    if rank4 && (dims.len() != 4 || (dims[1] != 3 && dims[1] >= 0)) {
        return Err(contract(
            model,
            format!("input `{want}` has shape {dims:?}"),
        ));
    }
    check_batch(&dims, &format!("input `{want}`"), model)?;
    Ok(dims)
}

/// The batch dimension must be 1 or dynamic: the element scores one frame at a time.
fn check_batch(dims: &[i64], what: &str, model: &str) -> Result<(), ScorerError> {
    match dims.first() {
        Some(&n) if n >= 0 && n != 1 => Err(contract(
            model,
            format!(
                "{what} has shape {dims:?}: a fixed batch dimension of {n} (must be 1 or dynamic)"
            ),
        )),
        _ => Ok(()),
    }
}

fn check_inputs_count(session: &Session, n: usize, model: &str) -> Result<(), ScorerError> {
    let names: Vec<&str> = session.inputs().iter().map(|i| i.name()).collect();
    if names.len() != n {
        return Err(contract(
            model,
            format!("it has {} inputs {names:?}", names.len()),
        ));
    }
    Ok(())
}

fn check_output(
    session: &Session,
    want: &str,
    utility: bool,
    model: &str,
) -> Result<Vec<i64>, ScorerError> {
    let dims = float32_dims(
        "output",
        session.outputs().iter().map(|o| (o.name(), o.dtype())),
        want,
        model,
    )?;
    if utility && !(dims.len() == 1 || (dims.len() == 2 && (dims[1] == 1 || dims[1] < 0))) {
        return Err(contract(
            model,
            format!("output `{want}` has shape {dims:?}"),
        ));
    }
    check_batch(&dims, &format!("output `{want}`"), model)?;
    Ok(dims)
}

/// Check a pair model against the contract and merge it with the metadata.
pub(super) fn validate_pair(session: &Session, model: &str) -> Result<ModelInfo, ScorerError> {
    let r = input_dims(session, "reference", true, model)?;
    let c = input_dims(session, "current", true, model)?;
    check_inputs_count(session, 2, model)?;
    check_output(session, "utility", true, model)?;
    if (r[2], r[3]) != (c[2], c[3]) {
        return Err(contract(
            model,
            format!("inputs `reference` and `current` differ in size ({r:?} vs {c:?})"),
        ));
    }
    read_metadata(session, (r[3], r[2]), model)
}

/// The encoder of a split model: `image` [N,3,H,W] → `features`. Returns the features' shape too.
pub(super) fn validate_encoder(
    session: &Session,
    model: &str,
) -> Result<(ModelInfo, Vec<i64>), ScorerError> {
    let d = input_dims(session, "image", true, model).map_err(split_hint)?;
    check_inputs_count(session, 1, model).map_err(split_hint)?;
    let features = check_output(session, "features", false, model).map_err(split_hint)?;
    Ok((read_metadata(session, (d[3], d[2]), model)?, features))
}

/// The head of a split model: `reference_features`, `current_features` → `utility`, whose fixed
/// feature dimensions must agree with the encoder's `features` output.
pub(super) fn validate_head(
    session: &Session,
    model: &str,
    encoder_features: &[i64],
) -> Result<(), ScorerError> {
    for input in ["reference_features", "current_features"] {
        let d = input_dims(session, input, false, model).map_err(split_hint)?;
        let clash = d.len() != encoder_features.len()
            || d.iter()
                .zip(encoder_features)
                .skip(1)
                .any(|(&h, &e)| h >= 0 && e >= 0 && h != e);
        if clash {
            return Err(split_hint(contract(
                model,
                format!(
                    "input `{input}` has shape {d:?}, the encoder's `features` output has shape \
                     {encoder_features:?}"
                ),
            )));
        }
    }
    check_inputs_count(session, 2, model).map_err(split_hint)?;
    check_output(session, "utility", true, model)
        .map(|_| ())
        .map_err(split_hint)
}

fn split_hint(e: ScorerError) -> ScorerError {
    match e {
        ScorerError::Contract { model, reason } => ScorerError::Contract {
            model,
            reason: format!(
                "{reason} (a split model is an encoder `image` [N,3,H,W] → `features` and a head \
                 (`reference_features`, `current_features`) → `utility`)"
            ),
        },
        e => e,
    }
}

/// `leangate.kind`: `pair` (default), `encoder` or `head`.
pub(super) fn model_kind(session: &Session, model: &str) -> Result<&'static str, ScorerError> {
    let meta = session.metadata().map_err(|e| ScorerError::Metadata {
        model: model.to_string(),
        reason: format!("unreadable: {e}"),
    })?;
    match meta.custom("leangate.kind").as_deref().map(str::trim) {
        None | Some("") | Some("pair") => Ok("pair"),
        Some("encoder") => Ok("encoder"),
        Some("head") => Ok("head"),
        Some(other) => Err(ScorerError::Metadata {
            model: model.to_string(),
            reason: format!("leangate.kind = {other:?}, expected `pair`, `encoder` or `head`"),
        }),
    }
}

/// The head file named by the encoder's `leangate.head`: a relative path resolved inside the
/// encoder's folder. Absolute paths, `..` and symbolic links leading out of that folder are
/// refused.
pub(super) fn head_path(
    encoder: &Path,
    session: &Session,
    model: &str,
) -> Result<PathBuf, ScorerError> {
    let meta_err = |reason: String| ScorerError::Metadata {
        model: model.to_string(),
        reason,
    };
    let meta = session
        .metadata()
        .map_err(|e| meta_err(format!("unreadable: {e}")))?;
    let name = meta
        .custom("leangate.head")
        .filter(|h| !h.trim().is_empty())
        .ok_or_else(|| {
            meta_err(
                "a split encoder (leangate.kind = encoder) must name its head file in \
                 leangate.head"
                    .into(),
            )
        })?;
    let name = name.trim();
    let rel = Path::new(name);
    if !rel
        .components()
        .all(|c| matches!(c, Component::Normal(_) | Component::CurDir))
    {
        return Err(meta_err(format!(
            "leangate.head = {name:?} must be a file name relative to the encoder's folder (no \
             absolute path, no `..`)"
        )));
    }
    let dir = encoder.parent().unwrap_or(Path::new("."));
    let dir = if dir.as_os_str().is_empty() {
        Path::new(".")
    } else {
        dir
    };
    let path = dir.join(rel);
    if let (Ok(d), Ok(p)) = (dir.canonicalize(), path.canonicalize()) {
        if !p.starts_with(&d) {
            return Err(meta_err(format!(
                "leangate.head = {name:?} resolves to `{}`, outside the encoder's folder `{}`",
                p.display(),
                d.display()
            )));
        }
    }
    Ok(path)
}

/// Merge the graph's input size (`(W, H)`, negative = dynamic) with the `leangate.*` metadata.
pub(super) fn read_metadata(
    session: &Session,
    size: (i64, i64),
    model: &str,
) -> Result<ModelInfo, ScorerError> {
    let meta_err = |reason: String| ScorerError::Metadata {
        model: model.to_string(),
        reason,
    };
    let meta = session
        .metadata()
        .map_err(|e| meta_err(format!("unreadable: {e}")))?;
    let get = |k: &str| meta.custom(k).filter(|v| !v.trim().is_empty());
    // A side the graph fixes: 0 is no size (not a dynamic one), and one beyond the largest
    // input is said with its own value.
    for (side, d) in [("W", size.0), ("H", size.1)] {
        if d == 0 || d > MAX_INPUT_SIDE as i64 {
            return Err(contract(
                model,
                format!(
                    "the graph fixes its input's {side} to {d} (each side 1 to {MAX_INPUT_SIDE})"
                ),
            ));
        }
    }
    let fixed = |d: i64| (d > 0).then(|| u32::try_from(d).unwrap_or(u32::MAX));
    let (gw, gh) = (fixed(size.0), fixed(size.1));
    let (width, height) = match get("leangate.input_size") {
        Some(s) => {
            let sz = parse_size(&s).ok_or_else(|| {
                meta_err(format!(
                    "leangate.input_size = {s:?}, expected `WxH` like `256x256`"
                ))
            })?;
            if gw.is_some_and(|w| w != sz.0) || gh.is_some_and(|h| h != sz.1) {
                return Err(meta_err(format!(
                    "leangate.input_size {s} disagrees with the graph's input (W {}, H {})",
                    gw.map_or("dynamic".to_string(), |w| w.to_string()),
                    gh.map_or("dynamic".to_string(), |h| h.to_string()),
                )));
            }
            sz
        }
        None => match (gw, gh) {
            (Some(w), Some(h)) => (w, h),
            (None, None) => DEFAULT_INPUT_SIZE,
            (w, h) => {
                return Err(meta_err(format!(
                    "the graph fixes only one side of its input (W {}, H {}) and \
                     leangate.input_size is absent: set leangate.input_size to `WxH`",
                    w.map_or("dynamic".to_string(), |w| w.to_string()),
                    h.map_or("dynamic".to_string(), |h| h.to_string()),
                )))
            }
        },
    };
    check_input_size(width, height, model)?;
    let resize = match get("leangate.resize") {
        Some(s) => ResizeMode::parse(&s).ok_or_else(|| {
            meta_err(format!(
                "leangate.resize = {s:?}, expected `short-side-crop` or `stretch`"
            ))
        })?,
        None => ResizeMode::ShortSideCrop,
    };
    let triplet = |key: &str, default: [f32; 3]| -> Result<[f32; 3], ScorerError> {
        match get(key) {
            Some(s) => parse_triplet(&s)
                .ok_or_else(|| meta_err(format!("{key} = {s:?}, expected three numbers"))),
            None => Ok(default),
        }
    };
    let mean = triplet("leangate.mean", [0.0; 3])?;
    let std = triplet("leangate.std", [1.0; 3])?;
    if mean.iter().any(|m| !m.is_finite()) {
        return Err(meta_err(format!(
            "leangate.mean = {mean:?} must be three finite numbers"
        )));
    }
    if std.iter().any(|s| !s.is_finite() || s.abs() < MIN_STD) {
        return Err(meta_err(format!(
            "leangate.std = {std:?} must be three finite numbers of magnitude at least {MIN_STD}"
        )));
    }
    // A number in a range, or absent; anything else is refused naming the key.
    let number = |key: &str, inside: fn(f64) -> bool, range: &str| match get(key) {
        Some(s) => s
            .trim()
            .parse::<f64>()
            .ok()
            .filter(|v| v.is_finite())
            .ok_or_else(|| meta_err(format!("{key} = {s:?} is not a number")))
            .and_then(|v| {
                if inside(v) {
                    Ok(Some(v))
                } else {
                    Err(meta_err(format!("{key} = {v} is outside {range}")))
                }
            }),
        None => Ok(None),
    };
    let threshold = number("leangate.threshold", |t| (0.0..=1.0).contains(&t), "[0, 1]")?;
    let score_max = number("leangate.score_max", |m| m > 0.0 && m <= 1.0, "(0, 1]")?;
    let score_step = number("leangate.score_step", |m| m > 0.0 && m <= 1.0, "(0, 1]")?;
    let geometry = match get("leangate.geometry") {
        Some(s) => Some(
            crate::geometry::Fusion::parse(&s)
                .map_err(|e| meta_err(format!("leangate.geometry: {e}")))?
                .with_score_max(score_max.unwrap_or(1.0))
                .with_score_step(score_step),
        ),
        None => None,
    };
    let name = get("leangate.name")
        .or_else(|| meta.name())
        .unwrap_or_else(|| model.trim_matches('`').to_string());
    Ok(ModelInfo {
        name,
        spec: TensorSpec {
            width,
            height,
            resize,
            mean,
            std,
        },
        threshold,
        calibration: get("leangate.calibration"),
        geometry,
        score_max,
        score_step,
        precision: get("leangate.precision").unwrap_or_else(|| "fp32".to_string()),
    })
}

/// Whether `input` and `output` of the graph both have a dynamic first (batch) dimension, so
/// that several frames can be run as one batch.
pub(super) fn dynamic_batch(session: &Session, input: &str, output: &str) -> bool {
    let first = |vt: &ValueType| tensor_dims(vt).and_then(|(_, d)| d.first().copied());
    let i = session
        .inputs()
        .iter()
        .find(|i| i.name() == input)
        .and_then(|i| first(i.dtype()));
    let o = session
        .outputs()
        .iter()
        .find(|o| o.name() == output)
        .and_then(|o| first(o.dtype()));
    matches!((i, o), (Some(a), Some(b)) if a < 0 && b < 0)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn parsers_and_bounds() {
        assert_eq!(parse_size("256x192"), Some((256, 192)));
        assert_eq!(parse_size(" 64 X 32 "), Some((64, 32)));
        assert_eq!(parse_size("0x5"), None);
        assert_eq!(parse_size("256"), None);
        assert_eq!(
            parse_triplet("0.485, 0.456, 0.406"),
            Some([0.485, 0.456, 0.406])
        );
        assert_eq!(parse_triplet("1 2 3"), Some([1.0, 2.0, 3.0]));
        assert_eq!(parse_triplet("1,2"), None);
        assert!(check_input_size(2048, 2048, "m").is_ok());
        let e = check_input_size(100_000, 100_000, "m").unwrap_err();
        assert!(e.to_string().contains("too large"), "{e}");
        assert!(check_input_size(4096, 4096, "m").is_err(), "192 MiB");
        assert!(check_input_size(4097, 1, "m").is_err());
    }
}

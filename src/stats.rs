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
    /// `frames_kept / frames_in` (0 before the first frame).
    pub keep_ratio: f64,
    /// Mean preprocessing + inference time per scored frame, microseconds.
    pub inference_mean_us: f64,
    /// 99th percentile of that time, microseconds.
    pub inference_p99_us: u64,
    /// The execution provider in use (`cpu`, `cuda`, `tensorrt`).
    pub execution_provider: String,
    /// The model's name.
    pub model: String,
    /// The threshold in force.
    pub threshold: f64,
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
            .field("keep-ratio", self.keep_ratio)
            .field("inference-mean-us", self.inference_mean_us)
            .field("inference-p99-us", self.inference_p99_us)
            .field("execution-provider", self.execution_provider.as_str())
            .field("model", self.model.as_str())
            .field("threshold", self.threshold)
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
            keep_ratio: get(s, "keep-ratio")?,
            inference_mean_us: get(s, "inference-mean-us")?,
            inference_p99_us: get(s, "inference-p99-us")?,
            execution_provider: get(s, "execution-provider")?,
            model: get(s, "model")?,
            threshold: get(s, "threshold")?,
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

/// Per-frame inference times, for the mean and 99th percentile.
#[derive(Debug, Clone, Default)]
pub struct InferenceStats {
    samples_us: Vec<u64>,
    sum_us: u128,
}

impl InferenceStats {
    pub fn record(&mut self, us: u64) {
        self.samples_us.push(us);
        self.sum_us += us as u128;
    }

    #[cfg(test)]
    fn count(&self) -> usize {
        self.samples_us.len()
    }

    /// Mean in microseconds (0 with no sample).
    pub fn mean_us(&self) -> f64 {
        if self.samples_us.is_empty() {
            0.0
        } else {
            self.sum_us as f64 / self.samples_us.len() as f64
        }
    }

    /// Nearest-rank percentile `p` in (0, 100], microseconds (0 with no sample).
    pub fn percentile_us(&self, p: f64) -> u64 {
        if self.samples_us.is_empty() {
            return 0;
        }
        let mut v = self.samples_us.clone();
        let rank = ((p / 100.0) * v.len() as f64).ceil().max(1.0) as usize;
        let idx = rank.min(v.len()) - 1;
        *v.select_nth_unstable(idx).1
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
        assert_eq!(s.percentile_us(99.0), 198);
        assert_eq!(s.percentile_us(100.0), 200);
        assert_eq!(s.percentile_us(50.0), 100);
    }

    #[test]
    fn stats_message_round_trip_and_errors() {
        gst::init().unwrap();
        let m = StatsMessage {
            frames_in: 10,
            frames_kept: 3,
            keep_ratio: 0.3,
            inference_mean_us: 812.5,
            inference_p99_us: 1400,
            execution_provider: "cpu".into(),
            model: "leangate-s".into(),
            threshold: 0.5,
        };
        let s = m.to_structure();
        assert_eq!(s.name(), STATS_MESSAGE);
        assert_eq!(s.get::<u64>("frames-kept").unwrap(), 3);
        assert_eq!(StatsMessage::from_structure(&s).unwrap(), m);
        let mut broken = s.clone();
        broken.remove_field("threshold");
        let e = StatsMessage::from_structure(&broken).unwrap_err();
        assert!(e.to_string().contains("threshold"), "{e}");
        let other = gst::Structure::new_empty("something-else");
        assert!(StatsMessage::from_structure(&other).is_err());
    }
}

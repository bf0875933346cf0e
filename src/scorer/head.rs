//! What remote scoring (`crate::remote`) needs from a loaded split model: the feature shape its
//! head takes, and the head run on features computed elsewhere (the encoder on a server).

use ort::value::{TensorRef, ValueType};

use super::{first_utility, Kind, Scorer, ScorerError};

impl Scorer {
    /// The shape of the head's `current_features` input (-1 for a variable dimension); `None`
    /// for a pair model.
    pub(crate) fn head_feature_dims(&self) -> Option<Vec<i64>> {
        let Kind::Split { head, .. } = &self.model.kind else {
            return None;
        };
        super::lock(head)
            .inputs()
            .iter()
            .find(|i| i.name() == "current_features")
            .and_then(|i| match i.dtype() {
                ValueType::Tensor { shape, .. } => Some(shape.iter().copied().collect()),
                _ => None,
            })
    }

    /// Run the split model's head on two feature tensors (`shape`, `data`); an error for a pair
    /// model.
    pub(crate) fn run_head(
        &mut self,
        reference: (&[usize], &[f32]),
        current: (&[usize], &[f32]),
    ) -> Result<f32, ScorerError> {
        let model = self.model.clone();
        let Kind::Split { head, .. } = &model.kind else {
            return Err(ScorerError::Inference("a pair model has no head".into()));
        };
        let inf = |e: ort::Error| ScorerError::Inference(e.to_string());
        let r = TensorRef::from_array_view((reference.0.to_vec(), reference.1)).map_err(inf)?;
        let c = TensorRef::from_array_view((current.0.to_vec(), current.1)).map_err(inf)?;
        let mut head = super::lock(head);
        let stop = self.stop.clone();
        let outputs = stop.run(
            &mut head,
            ort::inputs!["reference_features" => r, "current_features" => c],
        )?;
        super::check_utility(first_utility(&outputs)?)
    }
}

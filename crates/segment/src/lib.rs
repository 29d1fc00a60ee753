//! Learned fruit segmentation: a small fully convolutional ONNX network, run by the pure-Rust
//! runtime tract, as a [`FruitDetector`].
//!
//! The model contract (what `detector-service/model/train.py` exports): one input `rgb`,
//! `f32 [1, 3, H, W]` with RGB8 / 255, and one output, `f32 [1, 1, H, W]`, the probability that
//! each pixel shows fruit. The network is loaded from bytes (the caller reads the file) and
//! checked on a small probe image, so a wrong file fails at start-up with a clear error, not on
//! the first frame. Plans are optimised per image size and kept for the last size seen.

use std::sync::{Arc, Mutex};

use glasshouse_detect::{DetectError, FruitDetector};
use tract_onnx::prelude::*;

/// Side of the probe image the model is checked on when it is loaded.
const PROBE_SIZE: (u32, u32) = (16, 12);

type Plan = Arc<TypedRunnableModel<TypedModel>>;

/// A fruit segmentation network; cheap to share between threads.
pub struct OnnxFruitModel {
    model: InferenceModel,
    /// The optimised plan for the last image size, `(width, height)`.
    plan: Mutex<Option<((u32, u32), Plan)>>,
}

fn model_error(context: &str, e: impl std::fmt::Display) -> DetectError {
    DetectError::Model(format!("{context}: {e}"))
}

impl OnnxFruitModel {
    /// Parses an ONNX file's bytes and checks the contract on a probe image.
    pub fn from_bytes(onnx: &[u8]) -> Result<Self, DetectError> {
        let model = tract_onnx::onnx()
            .model_for_read(&mut std::io::Cursor::new(onnx))
            .map_err(|e| model_error("not a readable ONNX model", e))?;
        if model.input_outlets().map(|i| i.len()).unwrap_or(0) != 1 {
            return Err(DetectError::Model(
                "the model must have exactly one input (rgb, f32 [1, 3, H, W])".into(),
            ));
        }
        let loaded = Self {
            model,
            plan: Mutex::new(None),
        };
        let (w, h) = PROBE_SIZE;
        let probe = vec![128u8; (3 * w * h) as usize];
        loaded.probabilities(&probe, w, h)?;
        Ok(loaded)
    }

    /// The optimised plan for `width` × `height` images, built on first use of that size.
    fn plan_for(&self, width: u32, height: u32) -> Result<Plan, DetectError> {
        let mut cached = self
            .plan
            .lock()
            .map_err(|_| DetectError::Model("a previous run panicked".into()))?;
        if let Some((size, plan)) = cached.as_ref() {
            if *size == (width, height) {
                return Ok(plan.clone());
            }
        }
        let shape = [1, 3, height as usize, width as usize];
        let plan = self
            .model
            .clone()
            .with_input_fact(0, f32::fact(shape).into())
            .and_then(|m| m.into_optimized())
            .and_then(|m| m.into_runnable())
            .map_err(|e| model_error("the model does not fit a [1, 3, H, W] rgb input", e))?;
        let plan = Arc::new(plan);
        *cached = Some(((width, height), plan.clone()));
        Ok(plan)
    }

    /// One fruit probability per pixel of a row-major RGB8 image.
    pub fn probabilities(
        &self,
        rgb: &[u8],
        width: u32,
        height: u32,
    ) -> Result<Vec<f32>, DetectError> {
        let pixels = width as usize * height as usize;
        if rgb.len() != 3 * pixels || pixels == 0 {
            return Err(DetectError::Model(format!(
                "{} rgb bytes for a {width}x{height} image",
                rgb.len()
            )));
        }
        let plan = self.plan_for(width, height)?;
        // Interleaved RGB8 to planar f32 in [0, 1].
        let mut planar = vec![0f32; 3 * pixels];
        for (pixel, colour) in rgb.chunks_exact(3).enumerate() {
            for (channel, &value) in colour.iter().enumerate() {
                if let Some(slot) = planar.get_mut(channel * pixels + pixel) {
                    *slot = f32::from(value) / 255.0;
                }
            }
        }
        let input = Tensor::from_shape(&[1, 3, height as usize, width as usize], &planar)
            .map_err(|e| model_error("building the input", e))?;
        let outputs = plan
            .run(tvec!(input.into()))
            .map_err(|e| model_error("running the model", e))?;
        let output = outputs
            .first()
            .ok_or_else(|| DetectError::Model("the model has no output".into()))?;
        let view = output
            .to_array_view::<f32>()
            .map_err(|e| model_error("the output is not f32", e))?;
        if view.shape() != [1, 1, height as usize, width as usize] {
            return Err(DetectError::Model(format!(
                "the output has shape {:?}, expected [1, 1, {height}, {width}]",
                view.shape()
            )));
        }
        Ok(view.iter().copied().collect())
    }
}

impl FruitDetector for OnnxFruitModel {
    fn name(&self) -> &str {
        "onnx"
    }

    fn pixel_probabilities(
        &self,
        rgb: &[u8],
        width: u32,
        height: u32,
    ) -> Result<Option<Vec<f32>>, DetectError> {
        self.probabilities(rgb, width, height).map(Some)
    }

    fn voxel_confidence(&self, _mean_rgb: [u8; 3], mean_probability: Option<f32>) -> f32 {
        mean_probability.unwrap_or(0.0)
    }
}

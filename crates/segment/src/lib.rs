//! Learned fruit segmentation: a small fully convolutional ONNX network, run by the pure-Rust
//! runtime tract, as a [`FruitDetector`].
//!
//! The model contract (what `detector-service/model/train.py` exports): one input, `rgb`
//! `f32 [1, 3, H, W]` with RGB8 / 255, and one output, `f32 [1, 1, H, W]`, the probability that
//! each pixel shows fruit. A model whose layers work on a coarser grid states the multiple its
//! height and width must have in its metadata (`size_multiple`, 1 when absent); the image is
//! then padded with zeros at the bottom and right up to it and the output cropped back. The
//! network is loaded from bytes (the caller reads the file) and checked, input and probe image,
//! so a wrong file fails at start-up with a clear error, not on the first frame. Plans are
//! optimised per image size and kept for the last size seen.

use std::sync::{Arc, Mutex};

use glasshouse_detect::{DetectError, FruitDetector};
use tract_onnx::pb::{tensor_shape_proto::dimension, type_proto, ModelProto};
use tract_onnx::prelude::*;

/// Side of the probe image the model is checked on when it is loaded.
const PROBE_SIZE: (u32, u32) = (16, 12);
/// Largest `size_multiple` accepted (beyond it the metadata is surely wrong).
const MAX_SIZE_MULTIPLE: usize = 64;
/// Channels of the input the detector feeds: R, G, B.
const CHANNELS: usize = 3;

type Plan = Arc<TypedRunnableModel<TypedModel>>;

/// A fruit segmentation network; cheap to share between threads.
pub struct OnnxFruitModel {
    model: InferenceModel,
    size_multiple: usize,
    /// The optimised plan for the last (padded) image size, `(width, height)`.
    plan: Mutex<Option<((usize, usize), Plan)>>,
}

fn model_error(context: &str, e: impl std::fmt::Display) -> DetectError {
    DetectError::Model(format!("{context}: {e}"))
}

/// Checks that the graph's one input (the first that is not a weight) has 3 channels.
fn check_input(proto: &ModelProto) -> Result<(), DetectError> {
    let graph = proto
        .graph
        .as_ref()
        .ok_or_else(|| DetectError::Model("the ONNX file holds no graph".into()))?;
    let weights: Vec<&str> = graph.initializer.iter().map(|t| t.name.as_str()).collect();
    let inputs: Vec<_> = graph
        .input
        .iter()
        .filter(|i| !weights.contains(&i.name.as_str()))
        .collect();
    let [input] = inputs.as_slice() else {
        return Err(DetectError::Model(format!(
            "the model must have exactly one input (rgb, f32 [1, 3, H, W]), it has {}",
            inputs.len()
        )));
    };
    let channels = input
        .r#type
        .as_ref()
        .and_then(|t| t.value.as_ref())
        .and_then(|type_proto::Value::TensorType(t)| t.shape.as_ref())
        .and_then(|s| s.dim.get(1))
        .and_then(|d| match d.value {
            Some(dimension::Value::DimValue(c)) => Some(c),
            _ => None,
        });
    match channels {
        Some(3) => Ok(()),
        other => Err(DetectError::Model(format!(
            "input {:?} has {} channels; the detector feeds 3 (rgb, f32 [1, 3, H, W])",
            input.name,
            other.map_or("unknown".to_string(), |c| c.to_string())
        ))),
    }
}

/// The `size_multiple` of the model's metadata, 1 when absent.
fn size_multiple_of(proto: &ModelProto) -> Result<usize, DetectError> {
    let Some(entry) = proto
        .metadata_props
        .iter()
        .find(|p| p.key == "size_multiple")
    else {
        return Ok(1);
    };
    match entry.value.trim().parse::<usize>() {
        Ok(m) if (1..=MAX_SIZE_MULTIPLE).contains(&m) => Ok(m),
        _ => Err(DetectError::Model(format!(
            "metadata size_multiple {:?} is not an integer in 1..={MAX_SIZE_MULTIPLE}",
            entry.value
        ))),
    }
}

impl OnnxFruitModel {
    /// Parses an ONNX file's bytes and checks the contract on a probe image.
    pub fn from_bytes(onnx: &[u8]) -> Result<Self, DetectError> {
        let framework = tract_onnx::onnx();
        let proto = framework
            .proto_model_for_read(&mut std::io::Cursor::new(onnx))
            .map_err(|e| model_error("not a readable ONNX model", e))?;
        check_input(&proto)?;
        let size_multiple = size_multiple_of(&proto)?;
        let model = framework
            .model_for_proto_model(&proto)
            .map_err(|e| model_error("not a readable ONNX model", e))?;
        if model.input_outlets().map(|i| i.len()).unwrap_or(0) != 1 {
            return Err(DetectError::Model(
                "the model must have exactly one input (rgb, f32 [1, 3, H, W])".into(),
            ));
        }
        let loaded = Self {
            model,
            size_multiple,
            plan: Mutex::new(None),
        };
        let (w, h) = PROBE_SIZE;
        let probe = vec![128u8; (3 * w * h) as usize];
        loaded.probabilities(&probe, w, h)?;
        Ok(loaded)
    }

    /// The multiple the model needs its input's height and width to have (images are padded
    /// up to it).
    pub fn size_multiple(&self) -> usize {
        self.size_multiple
    }

    /// The optimised plan for `width` × `height` (padded) inputs, built on first use of that
    /// size.
    fn plan_for(&self, width: usize, height: usize) -> Result<Plan, DetectError> {
        let mut cached = self
            .plan
            .lock()
            .map_err(|_| DetectError::Model("a previous run panicked".into()))?;
        if let Some((size, plan)) = cached.as_ref() {
            if *size == (width, height) {
                return Ok(plan.clone());
            }
        }
        let shape = [1, CHANNELS, height, width];
        let plan = self
            .model
            .clone()
            .with_input_fact(0, f32::fact(shape).into())
            .and_then(|m| m.into_optimized())
            .and_then(|m| m.into_runnable())
            .map_err(|e| {
                model_error(
                    &format!("the model does not fit a {shape:?} input"),
                    format!("{e:#}"),
                )
            })?;
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
        let (w, h) = (width as usize, height as usize);
        let pixels = w * h;
        if rgb.len() != 3 * pixels || pixels == 0 {
            return Err(DetectError::Model(format!(
                "{} rgb bytes for a {width}x{height} image",
                rgb.len()
            )));
        }
        // Zero rows and columns at the bottom and right up to the model's size multiple.
        let m = self.size_multiple;
        let (pw, ph) = (w.div_ceil(m) * m, h.div_ceil(m) * m);
        let plan = self.plan_for(pw, ph)?;
        let plane = pw * ph;
        // Interleaved RGB8 to planar f32 in [0, 1].
        let mut planar = vec![0f32; CHANNELS * plane];
        for (y, row) in rgb.chunks_exact(3 * w).enumerate() {
            for (x, colour) in row.chunks_exact(3).enumerate() {
                for (channel, &value) in colour.iter().enumerate() {
                    if let Some(slot) = planar.get_mut(channel * plane + y * pw + x) {
                        *slot = f32::from(value) / 255.0;
                    }
                }
            }
        }
        let input = Tensor::from_shape(&[1, CHANNELS, ph, pw], &planar)
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
        if view.shape() != [1, 1, ph, pw] {
            return Err(DetectError::Model(format!(
                "the output has shape {:?}, expected [1, 1, {ph}, {pw}]",
                view.shape()
            )));
        }
        if (pw, ph) == (w, h) {
            return Ok(view.iter().copied().collect());
        }
        Ok(view
            .iter()
            .enumerate()
            .filter(|(i, _)| i % pw < w && i / pw < h)
            .map(|(_, &p)| p)
            .collect())
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

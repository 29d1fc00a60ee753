//! Fruit detection: RGB-D frame to ROI-labelled world point cloud (the paper's HSI rule).
//!
//! [`detect`] back-projects every valid depth pixel into the camera frame, moves it to the world
//! with `world_from_camera`, averages points and colours per world voxel (like PCL's `VoxelGrid`
//! at the map resolution), and labels each averaged point as ROI (fruit) when its colour passes the
//! paper's HSI rule ([`HsiRule`], PCL's integer HSI from [`rgb_to_hsi`]). The output is ordered by
//! voxel key, so it is deterministic. The simulation path of the paper; the real-world path would
//! replace the colour rule with an instance-segmentation mask.

use std::collections::HashMap;
use std::hash::{BuildHasherDefault, Hasher};

use glasshouse_geom::CameraIntrinsics;
use nalgebra::{Isometry3, Point3};

/// The paper's colour rule on PCL's integer HSI (hue in [-128, 127] for [-180°, 180°)).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct HsiRule {
    pub hue_min: i32,
    pub hue_max: i32,
    pub saturation_min: i32,
    pub intensity_min: i32,
}

impl Default for HsiRule {
    /// The authors' hue and saturation (hue -20..=35, about -28° to +49°; saturation ≥ 30) with
    /// intensity ≥ 12 instead of their 30: under a glasshouse's shade (`--shadows`) red fruit
    /// falls to an intensity of 20-30 and the authors' floor missed 83 % of the fruit pixels of
    /// one frame (scenario 2, seed 3); hue and saturation alone still tell it from leaves,
    /// stems and floor.
    fn default() -> Self {
        Self {
            intensity_min: 12,
            ..Self::authors()
        }
    }
}

impl HsiRule {
    /// The authors' code defaults: hue -20..=35, saturation and intensity ≥ 30.
    pub fn authors() -> Self {
        Self {
            hue_min: -20,
            hue_max: 35,
            saturation_min: 30,
            intensity_min: 30,
        }
    }
}

impl HsiRule {
    /// True when the colour is a region of interest (fruit).
    pub fn is_roi(&self, r: u8, g: u8, b: u8) -> bool {
        let (h, s, i) = rgb_to_hsi(r, g, b);
        (self.hue_min..=self.hue_max).contains(&h)
            && s >= self.saturation_min
            && i >= self.intensity_min
    }
}

/// PCL's integer HSI, exactly as `PackedHSIComparison` computes it: `(hue, saturation, intensity)`.
pub fn rgb_to_hsi(r: u8, g: u8, b: u8) -> (i32, i32, i32) {
    let (ri, gi, bi) = (r as i32, g as i32, b as i32);
    let hx = (2.0 * r as f32 - g as f32 - b as f32) / 4.0;
    let hy = (gi - bi) as f32 * 111.0 / 255.0;
    // `as i32` truncates toward zero, as the C++ int conversion does.
    let h = ((hy.atan2(hx) * 128.0 / std::f32::consts::PI) as i32).clamp(-128, 127);
    let i = (ri + gi + bi) / 3;
    let m = ri.min(gi).min(bi);
    let s = if i == 0 { 0 } else { 255 - (m * 255) / i };
    (h, s, i)
}

/// Fruit confidence (0 to 1) at and above which an averaged point is ROI.
pub const ROI_CONFIDENCE_THRESHOLD: f32 = 0.5;

/// Prior votes of a voxel's pixel vote: one for fruit, two for anything else (fruit is the rare
/// class). With them a voxel is fruit when at least (n + 1) / 2 of its n pixels say so: a
/// strict majority, a tie goes to not-fruit. Under 30 % label noise this keeps the count ratio
/// at 1.0 where the mean-colour rule reports 7 times the fruit (docs/results.md).
pub const PRIOR_FRUIT_VOTES: f32 = 1.0;
pub const PRIOR_OTHER_VOTES: f32 = 2.0;

/// What decides which points are fruit. Two stages: [`FruitDetector::pixel_probabilities`] runs
/// once per frame, [`FruitDetector::voxel_confidence`] once per averaged point. A detector that
/// labels pixels gets, per voxel, its pixels' votes with [`PRIOR_FRUIT_VOTES`] and
/// [`PRIOR_OTHER_VOTES`], `(Σ p + 1) / (n + 3)`: a voxel needs a majority of its pixels,
/// so scattered false labels (a noisy detector) rarely make fruit. A detector that labels only
/// voxels (`pixel_probabilities` gives `None`) sees the voxel's mean colour, as the paper's
/// colour rule does.
pub trait FruitDetector: Send + Sync {
    /// A short name for logs and reports (`hsi`, `onnx`).
    fn name(&self) -> &str;

    /// One fruit probability in [0, 1] per pixel of the row-major RGB8 image, or `None` when
    /// the detector labels voxels by their averaged colour alone.
    fn pixel_probabilities(&self, rgb: &[u8], width: u32, height: u32) -> Result<Option<Vec<f32>>>;

    /// The fruit confidence in [0, 1] of a voxel from its mean colour and, when
    /// [`FruitDetector::pixel_probabilities`] gave them, its pixels' smoothed vote
    /// `(Σ p + 1) / (n + 3)`.
    fn voxel_confidence(&self, mean_rgb: [u8; 3], mean_probability: Option<f32>) -> f32;
}

/// The HSI rule applied to every pixel, each voxel labelled by its pixels' smoothed vote; the
/// default detector. [`HsiRule`] itself labels each voxel by its mean colour (the paper's way),
/// which a noisy detector's scattered false pixels tip over easily.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct HsiVotes(pub HsiRule);

impl FruitDetector for HsiRule {
    fn name(&self) -> &str {
        "hsi-mean-colour"
    }

    fn pixel_probabilities(&self, _: &[u8], _: u32, _: u32) -> Result<Option<Vec<f32>>> {
        Ok(None)
    }

    fn voxel_confidence(&self, [r, g, b]: [u8; 3], _: Option<f32>) -> f32 {
        if self.is_roi(r, g, b) {
            1.0
        } else {
            0.0
        }
    }
}

impl FruitDetector for HsiVotes {
    fn name(&self) -> &str {
        "hsi"
    }

    fn pixel_probabilities(&self, rgb: &[u8], _: u32, _: u32) -> Result<Option<Vec<f32>>> {
        let votes = rgb
            .chunks_exact(3)
            .map(|p| f32::from(u8::from(self.0.is_roi(p[0], p[1], p[2]))))
            .collect();
        Ok(Some(votes))
    }

    fn voxel_confidence(&self, mean_rgb: [u8; 3], vote: Option<f32>) -> f32 {
        vote.unwrap_or_else(|| self.0.voxel_confidence(mean_rgb, None))
    }
}

/// Detector settings.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct DetectorConfig {
    /// Edge of the world voxels points are averaged in (the map resolution).
    pub voxel_size_m: f64,
    pub min_depth_m: f64,
    pub max_depth_m: f64,
    pub rule: HsiRule,
}

impl Default for DetectorConfig {
    fn default() -> Self {
        Self {
            voxel_size_m: 0.01,
            min_depth_m: 0.15,
            max_depth_m: 3.0,
            rule: HsiRule::default(),
        }
    }
}

/// One aligned RGB-D frame: depth in integer units (0 = invalid) and RGB8, both row-major.
#[derive(Clone, Copy, Debug)]
pub struct DepthFrame<'a> {
    pub intrinsics: CameraIntrinsics,
    pub depth: &'a [u16],
    /// Metres per depth unit, e.g. 0.001 for millimetres.
    pub depth_scale_m: f64,
    pub rgb: &'a [u8],
}

/// Down-sampled world points with their ROI labels (same length and order).
#[derive(Clone, Debug, PartialEq)]
pub struct LabelledCloud {
    pub points_in_world: Vec<Point3<f32>>,
    pub roi: Vec<bool>,
    /// Each point's fruit confidence in [0, 1] (a colour rule gives 0 or 1); `roi` is
    /// confidence >= [`ROI_CONFIDENCE_THRESHOLD`].
    pub confidence: Vec<f32>,
    /// Each point's colour: the integer mean of its pixels' RGB8 colours, what the colour rule
    /// judges.
    pub rgb: Vec<[u8; 3]>,
    /// Camera centre in the world: the origin of every ray for the map update.
    pub sensor_origin_in_world: Point3<f64>,
    /// Pixels skipped for zero or out-of-range depth.
    pub invalid_pixels: usize,
}

/// Why a frame could not be processed.
#[derive(thiserror::Error, Debug, Clone, PartialEq)]
pub enum DetectError {
    #[error(
        "frame size mismatch: depth has {depth_len} values and rgb {rgb_len} bytes, \
         expected {expected_depth_len} and {expected_rgb_len}"
    )]
    SizeMismatch {
        depth_len: usize,
        rgb_len: usize,
        expected_depth_len: usize,
        expected_rgb_len: usize,
    },
    #[error("camera intrinsics have a zero size or a non-finite or non-positive focal length")]
    InvalidIntrinsics,
    #[error("depth scale must be finite and positive, got {0}")]
    InvalidDepthScale(f64),
    #[error("camera pose contains a non-finite value")]
    NonFinitePose,
    #[error("invalid detector configuration: {0}")]
    InvalidConfig(String),
    #[error("the fruit model failed: {0}")]
    Model(String),
}

pub type Result<T, E = DetectError> = std::result::Result<T, E>;

/// Packed voxel keys hold 21 bits per axis, offset so that negative relative keys fit.
const KEY_BITS: u32 = 21;
const KEY_MASK: u64 = (1 << KEY_BITS) - 1;
const KEY_OFFSET: i64 = 1 << (KEY_BITS - 1);

/// Sums of one voxel's points and colours.
#[derive(Clone, Copy, Default)]
struct VoxelSum {
    position_m: [f64; 3],
    rgb: [u32; 3],
    /// Sum of the pixels' fruit probabilities (learned detectors only).
    probability: f32,
    count: u32,
}

impl VoxelSum {
    fn add(&mut self, other: &VoxelSum) {
        for a in 0..3 {
            self.position_m[a] += other.position_m[a];
            self.rgb[a] += other.rgb[a];
        }
        self.probability += other.probability;
        self.count += other.count;
    }
}

/// A cheap multiplicative hasher for packed voxel keys; the default SipHash costs more than the
/// rest of the pipeline.
#[derive(Default)]
struct KeyHasher(u64);

impl Hasher for KeyHasher {
    fn finish(&self) -> u64 {
        // Fold the well-mixed high bits down: the table indexes buckets by the low bits.
        let h = self.0;
        h ^ (h >> 29) ^ (h >> 41)
    }

    fn write(&mut self, bytes: &[u8]) {
        for &b in bytes {
            self.write_u64(b as u64);
        }
    }

    fn write_u64(&mut self, i: u64) {
        self.0 = (self.0.rotate_left(5) ^ i).wrapping_mul(0x51_7c_c1_b7_27_22_0a_95);
    }

    fn write_usize(&mut self, i: usize) {
        self.write_u64(i as u64);
    }
}

/// `floor` as an integer without a libm call (the baseline x86-64 target has no SSE4.1 `roundsd`).
/// Saturates for values beyond the i64 range, which the key range check then rejects.
#[inline]
fn floor_to_i64(x: f64) -> i64 {
    let truncated = x as i64;
    if (truncated as f64) > x {
        truncated - 1
    } else {
        truncated
    }
}

/// Adds a run of points to its voxel's sums, creating the voxel on first sight.
fn accumulate(
    voxels: &mut HashMap<u64, u32, BuildHasherDefault<KeyHasher>>,
    sums: &mut Vec<VoxelSum>,
    key: u64,
    run: &VoxelSum,
) {
    let next = sums.len() as u32;
    let index = *voxels.entry(key).or_insert(next);
    match sums.get_mut(index as usize) {
        Some(sum) => sum.add(run),
        None => sums.push(*run),
    }
}

fn validate(
    frame: &DepthFrame,
    world_from_camera: &Isometry3<f64>,
    config: &DetectorConfig,
) -> Result<()> {
    let k = &frame.intrinsics;
    if !k.is_valid() {
        return Err(DetectError::InvalidIntrinsics);
    }
    let expected_depth_len = k.pixel_count();
    let expected_rgb_len = 3 * expected_depth_len;
    if frame.depth.len() != expected_depth_len || frame.rgb.len() != expected_rgb_len {
        return Err(DetectError::SizeMismatch {
            depth_len: frame.depth.len(),
            rgb_len: frame.rgb.len(),
            expected_depth_len,
            expected_rgb_len,
        });
    }
    if !(frame.depth_scale_m.is_finite() && frame.depth_scale_m > 0.0) {
        return Err(DetectError::InvalidDepthScale(frame.depth_scale_m));
    }
    let pose_finite = world_from_camera
        .translation
        .vector
        .iter()
        .chain(world_from_camera.rotation.coords.iter())
        .all(|v| v.is_finite());
    if !pose_finite {
        return Err(DetectError::NonFinitePose);
    }
    if !(config.voxel_size_m.is_finite() && config.voxel_size_m > 0.0) {
        return Err(DetectError::InvalidConfig(format!(
            "voxel_size_m must be finite and positive, got {}",
            config.voxel_size_m
        )));
    }
    // Every point lies within max_depth * sqrt(3) of the camera on each axis (generously), which
    // must fit the packed relative voxel keys.
    if config.max_depth_m / config.voxel_size_m > (KEY_OFFSET / 4) as f64 {
        return Err(DetectError::InvalidConfig(format!(
            "max_depth_m / voxel_size_m must stay below {}, got {}",
            KEY_OFFSET / 4,
            config.max_depth_m / config.voxel_size_m
        )));
    }
    if !(config.min_depth_m.is_finite()
        && config.max_depth_m.is_finite()
        && config.min_depth_m >= 0.0
        && config.min_depth_m < config.max_depth_m)
    {
        return Err(DetectError::InvalidConfig(format!(
            "need 0 <= min_depth_m < max_depth_m (finite), got {} and {}",
            config.min_depth_m, config.max_depth_m
        )));
    }
    Ok(())
}

/// Turns one RGB-D frame into ROI-labelled, voxel-averaged points in the world frame, labelled
/// by the configured HSI rule's pixel votes ([`HsiVotes`]).
pub fn detect(
    frame: &DepthFrame,
    world_from_camera: &Isometry3<f64>,
    config: &DetectorConfig,
) -> Result<LabelledCloud> {
    detect_with(frame, world_from_camera, config, &HsiVotes(config.rule))
}

/// [`detect`] with the points labelled by `detector` instead of the configured HSI rule.
pub fn detect_with(
    frame: &DepthFrame,
    world_from_camera: &Isometry3<f64>,
    config: &DetectorConfig,
    detector: &dyn FruitDetector,
) -> Result<LabelledCloud> {
    validate(frame, world_from_camera, config)?;
    let pixel_probability =
        detector.pixel_probabilities(frame.rgb, frame.intrinsics.width, frame.intrinsics.height)?;
    if let Some(p) = &pixel_probability {
        if p.len() != frame.depth.len() {
            return Err(DetectError::Model(format!(
                "{} probabilities for {} pixels",
                p.len(),
                frame.depth.len()
            )));
        }
    }
    let k = frame.intrinsics;
    let width = k.width as usize;
    let rotation = world_from_camera.rotation.to_rotation_matrix();
    let r = rotation.matrix();
    let t = world_from_camera.translation.vector;
    let inv_voxel = 1.0 / config.voxel_size_m;

    // Per-column and per-row ray slopes, so each pixel costs a few multiplications.
    let x_slope: Vec<f64> = (0..k.width).map(|u| (u as f64 - k.cx) / k.fx).collect();
    let y_slope: Vec<f64> = (0..k.height).map(|v| (v as f64 - k.cy) / k.fy).collect();

    // Keys are packed into one u64 relative to the camera's voxel (21 bits per axis, x highest), so
    // hashing is one multiply and sorting the packed keys sorts by (x, y, z).
    let origin_key = [t.x, t.y, t.z].map(|c| floor_to_i64(c * inv_voxel));
    let pack = |key: [i64; 3]| -> u64 {
        let field = |a: usize| (key[a] - origin_key[a] + KEY_OFFSET) as u64 & KEY_MASK;
        (field(0) << 42) | (field(1) << 21) | field(2)
    };
    // Map from packed key to an index into `sums`: small table entries keep the probing in cache.
    let mut sums: Vec<VoxelSum> = Vec::with_capacity(frame.depth.len() / 4);
    let mut voxels: HashMap<u64, u32, BuildHasherDefault<KeyHasher>> =
        HashMap::with_capacity_and_hasher(frame.depth.len() / 4, Default::default());
    let mut invalid_pixels = 0usize;
    let mut run_key: Option<u64> = None;
    let mut run = VoxelSum::default();
    let rows = frame
        .depth
        .chunks_exact(width)
        .zip(frame.rgb.chunks_exact(3 * width));
    for (v, ((depth_row, rgb_row), &ys)) in rows.zip(&y_slope).enumerate() {
        let pixels = depth_row.iter().zip(rgb_row.chunks_exact(3)).zip(&x_slope);
        for (u, ((&raw, rgb), &xs)) in pixels.enumerate() {
            let depth_m = raw as f64 * frame.depth_scale_m;
            if raw == 0 || depth_m < config.min_depth_m || depth_m > config.max_depth_m {
                invalid_pixels += 1;
                continue;
            }
            let (xc, yc, zc) = (xs * depth_m, ys * depth_m, depth_m);
            let p = [
                r[(0, 0)] * xc + r[(0, 1)] * yc + r[(0, 2)] * zc + t.x,
                r[(1, 0)] * xc + r[(1, 1)] * yc + r[(1, 2)] * zc + t.y,
                r[(2, 0)] * xc + r[(2, 1)] * yc + r[(2, 2)] * zc + t.z,
            ];
            let key = p.map(|c| floor_to_i64(c * inv_voxel));
            if (0..3).any(|a| (key[a] - origin_key[a]).abs() >= KEY_OFFSET) {
                // Only reachable with absurd fields of view; such a point cannot be keyed.
                invalid_pixels += 1;
                continue;
            }
            let packed = pack(key);
            // Neighbouring pixels mostly share a voxel: accumulate runs and touch the map once per run.
            if run_key != Some(packed) {
                if let Some(k) = run_key {
                    accumulate(&mut voxels, &mut sums, k, &run);
                }
                run_key = Some(packed);
                run = VoxelSum::default();
            }
            for a in 0..3 {
                run.position_m[a] += p[a];
                run.rgb[a] += rgb[a] as u32;
            }
            if let Some(p) = &pixel_probability {
                run.probability += p.get(v * width + u).copied().unwrap_or(0.0);
            }
            run.count += 1;
        }
    }
    if let Some(k) = run_key {
        accumulate(&mut voxels, &mut sums, k, &run);
    }

    let mut cells: Vec<(u64, u32)> = voxels.into_iter().collect();
    cells.sort_unstable_by_key(|(key, _)| *key);
    let mut points_in_world = Vec::with_capacity(cells.len());
    let mut roi = Vec::with_capacity(cells.len());
    let mut confidence = Vec::with_capacity(cells.len());
    let mut colours = Vec::with_capacity(cells.len());
    for sum in cells.iter().filter_map(|&(_, i)| sums.get(i as usize)) {
        let n = sum.count.max(1);
        let mean = sum.position_m.map(|c| (c / n as f64) as f32);
        points_in_world.push(Point3::new(mean[0], mean[1], mean[2]));
        // Integer average of each channel, as PCL's VoxelGrid stores the averaged colour.
        let mean_rgb = sum.rgb.map(|c| (c / n).min(255) as u8);
        let vote = pixel_probability.is_some().then(|| {
            (sum.probability + PRIOR_FRUIT_VOTES)
                / (n as f32 + PRIOR_FRUIT_VOTES + PRIOR_OTHER_VOTES)
        });
        let c = detector.voxel_confidence(mean_rgb, vote);
        // NaN from a broken model is no evidence of fruit.
        let c = if c.is_finite() {
            c.clamp(0.0, 1.0)
        } else {
            0.0
        };
        roi.push(c >= ROI_CONFIDENCE_THRESHOLD);
        confidence.push(c);
        colours.push(mean_rgb);
    }
    Ok(LabelledCloud {
        points_in_world,
        roi,
        confidence,
        rgb: colours,
        sensor_origin_in_world: Point3::from(t),
        invalid_pixels,
    })
}

#[cfg(test)]
mod tests {
    #![allow(clippy::unwrap_used)]

    use super::*;
    use glasshouse_geom::look_along;
    use nalgebra::Vector3;

    /// A frame of intrinsics `k` with depth in millimetres.
    fn mm_frame<'a>(k: CameraIntrinsics, depth: &'a [u16], rgb: &'a [u8]) -> DepthFrame<'a> {
        DepthFrame {
            intrinsics: k,
            depth,
            depth_scale_m: 0.001,
            rgb,
        }
    }

    #[test]
    fn hsi_of_known_colours() {
        let rule = HsiRule::default();
        assert_eq!(rgb_to_hsi(255, 0, 0), (0, 255, 85));
        assert!(rule.is_roi(255, 0, 0));
        let (h, s, _) = rgb_to_hsi(0, 200, 0);
        assert!(h > 35, "green hue {h}");
        assert_eq!(s, 255);
        assert!(!rule.is_roi(0, 200, 0));
        assert_eq!(rgb_to_hsi(128, 128, 128), (0, 0, 128));
        assert!(!rule.is_roi(128, 128, 128));
        assert_eq!(rgb_to_hsi(0, 0, 0), (0, 0, 0));
        assert!(!rule.is_roi(0, 0, 0));
        // Dark red: right hue and saturation, too dark for the authors' rule, not for ours.
        assert!(!HsiRule::authors().is_roi(80, 0, 0));
        assert!(HsiRule::authors().is_roi(100, 0, 0));
        assert!(rule.is_roi(40, 0, 0));
        assert!(!rule.is_roi(30, 0, 0));
        // Pure blue: atan2(-111, -63.75) = -119.9°, times 128/180 truncates to -85.
        assert_eq!(rgb_to_hsi(0, 0, 255).0, -85);
    }

    #[test]
    fn hue_band_edges() {
        let rule = HsiRule::default();
        // Orange-ish: hue 34 and 36 sit either side of the upper limit 35.
        let hue = |g: u8| rgb_to_hsi(255, g, 0).0;
        let inside = (0..=255u8).filter(|&g| hue(g) == 35).max().unwrap();
        let outside = (0..=255u8).find(|&g| hue(g) == 36).unwrap();
        assert!(rule.is_roi(255, inside, 0));
        assert!(!rule.is_roi(255, outside, 0));
        // Magenta side: hue -20 in, -21 out.
        let hue_b = |b: u8| rgb_to_hsi(255, 0, b).0;
        let inside = (0..=255u8).filter(|&b| hue_b(b) == -20).max().unwrap();
        let outside = (0..=255u8).find(|&b| hue_b(b) == -21).unwrap();
        assert!(rule.is_roi(255, 0, inside));
        assert!(!rule.is_roi(255, 0, outside));
        // Truncation toward zero: a tiny negative angle gives hue 0, not -1.
        assert_eq!(rgb_to_hsi(255, 0, 1).0, 0);
    }

    fn flat_frame(
        width: u32,
        height: u32,
        depth: u16,
        colour: [u8; 3],
    ) -> (CameraIntrinsics, Vec<u16>, Vec<u8>) {
        let k = CameraIntrinsics::from_horizontal_fov(width, height, 80f64.to_radians());
        let n = k.pixel_count();
        (k, vec![depth; n], colour.repeat(n))
    }

    #[test]
    fn flat_depth_lands_on_the_expected_world_plane() {
        // Camera 1.5 m above the floor looking straight down sees a plane at depth 1.5 m:
        // every point must land at z = 0 within the footprint of the field of view.
        let (k, depth, rgb) = flat_frame(64, 48, 1500, [200, 30, 20]);
        let frame = mm_frame(k, &depth, &rgb);
        let pose = look_along(&Point3::new(0.3, -0.2, 1.5), &(-Vector3::z()));
        let config = DetectorConfig {
            voxel_size_m: 0.05,
            ..Default::default()
        };
        let cloud = detect(&frame, &pose, &config).unwrap();
        assert_eq!(cloud.invalid_pixels, 0);
        assert_eq!(cloud.points_in_world.len(), cloud.roi.len());
        assert!(cloud.roi.iter().all(|&r| r));
        let half_width = 1.5 * (40f64.to_radians()).tan();
        let mut centroid = Vector3::zeros();
        for p in &cloud.points_in_world {
            assert!(p.coords.iter().all(|c| c.is_finite()));
            assert!(p.z.abs() < 1e-5, "{p}");
            assert!((p.x as f64 - 0.3).abs() <= half_width + 1e-3);
            centroid += p.coords.cast::<f64>();
        }
        centroid /= cloud.points_in_world.len() as f64;
        // Symmetric footprint around the point below the camera (voxel edges add a little skew).
        assert!(
            (centroid.x - 0.3).abs() < 0.03 && (centroid.y + 0.2).abs() < 0.03,
            "{centroid}"
        );
        assert_eq!(cloud.sensor_origin_in_world, Point3::new(0.3, -0.2, 1.5));
        // Output is sorted by voxel key.
        let keys: Vec<[i32; 3]> = cloud
            .points_in_world
            .iter()
            .map(|p| [p.x, p.y, p.z].map(|c| (c as f64 / 0.05).floor() as i32))
            .collect();
        assert!(keys.windows(2).all(|w| w[0] < w[1]));
    }

    #[test]
    fn centre_pixel_back_projects_along_the_optical_axis() {
        // 3x3 image, only the centre pixel valid, camera at (1, 2, 0.5) looking along +x.
        let k = CameraIntrinsics::from_horizontal_fov(3, 3, 1.0);
        let mut depth = vec![0u16; 9];
        depth[4] = 2000;
        let rgb = vec![10u8; 27];
        let frame = mm_frame(k, &depth, &rgb);
        let pose = look_along(&Point3::new(1.0, 2.0, 0.5), &Vector3::x());
        let cloud = detect(&frame, &pose, &DetectorConfig::default()).unwrap();
        assert_eq!(cloud.invalid_pixels, 8);
        assert_eq!(cloud.points_in_world.len(), 1);
        let p = cloud.points_in_world[0];
        assert!((p - Point3::new(3.0f32, 2.0, 0.5)).norm() < 1e-5, "{p}");
        assert!(!cloud.roi[0]);
    }

    #[test]
    fn many_pixels_in_one_voxel_average_to_their_mean() {
        // A far plane seen by a tiny, narrow camera: all pixels fall in one 1 m voxel.
        let k = CameraIntrinsics::from_horizontal_fov(4, 4, 0.02);
        let depth: Vec<u16> = (0..16).map(|i| 2000 + i as u16).collect();
        let rgb: Vec<u8> = (0..16)
            .flat_map(|i| [200 + (i % 2) as u8, 10, 20])
            .collect();
        let frame = mm_frame(k, &depth, &rgb);
        let pose = look_along(&Point3::new(0.5, 0.5, 0.5), &Vector3::x());
        let config = DetectorConfig {
            voxel_size_m: 1.0,
            ..Default::default()
        };
        let cloud = detect(&frame, &pose, &config).unwrap();
        assert_eq!(cloud.points_in_world.len(), 1);
        let mut mean = Vector3::zeros();
        for (i, &d) in depth.iter().enumerate() {
            let p_cam = k.backproject((i % 4) as f64, (i / 4) as f64, d as f64 * 0.001);
            mean += (pose * p_cam).coords;
        }
        mean /= 16.0;
        assert!((cloud.points_in_world[0].coords.cast::<f64>() - mean).norm() < 1e-5);
        // Colour average 200.5 truncates to 200; red stays ROI.
        assert!(cloud.roi[0]);
    }

    #[test]
    fn out_of_range_depth_is_invalid_and_output_is_nan_free() {
        let (k, mut depth, rgb) = flat_frame(8, 6, 1000, [0, 200, 0]);
        depth[0] = 0;
        depth[1] = 100; // 0.1 m: below the minimum
        depth[2] = 3500; // 3.5 m: beyond the maximum
        let frame = mm_frame(k, &depth, &rgb);
        let cloud = detect(&frame, &Isometry3::identity(), &DetectorConfig::default()).unwrap();
        assert_eq!(cloud.invalid_pixels, 3);
        assert!(cloud
            .points_in_world
            .iter()
            .all(|p| p.coords.iter().all(|c| c.is_finite())));
        assert!(cloud.roi.iter().all(|&r| !r));
    }

    #[test]
    fn bad_inputs_are_errors_not_panics() {
        let (k, depth, rgb) = flat_frame(8, 6, 1000, [200, 0, 0]);
        let id = Isometry3::identity();
        let cfg = DetectorConfig::default();
        let short = mm_frame(k, &depth[1..], &rgb);
        assert!(matches!(
            detect(&short, &id, &cfg),
            Err(DetectError::SizeMismatch { .. })
        ));
        let short_rgb = mm_frame(k, &depth, &rgb[3..]);
        assert!(matches!(
            detect(&short_rgb, &id, &cfg),
            Err(DetectError::SizeMismatch { .. })
        ));
        for scale in [0.0, -1.0, f64::NAN, f64::INFINITY] {
            let f = DepthFrame {
                intrinsics: k,
                depth: &depth,
                depth_scale_m: scale,
                rgb: &rgb,
            };
            assert!(matches!(
                detect(&f, &id, &cfg),
                Err(DetectError::InvalidDepthScale(_))
            ));
        }
        let good = mm_frame(k, &depth, &rgb);
        let nan_pose = Isometry3::translation(f64::NAN, 0.0, 0.0);
        assert_eq!(
            detect(&good, &nan_pose, &cfg),
            Err(DetectError::NonFinitePose)
        );
        let mut bad_k = k;
        bad_k.fx = f64::NAN;
        let f = DepthFrame {
            intrinsics: bad_k,
            ..good
        };
        assert_eq!(detect(&f, &id, &cfg), Err(DetectError::InvalidIntrinsics));
        let zero = DepthFrame {
            intrinsics: CameraIntrinsics::from_horizontal_fov(0, 0, 1.0),
            depth: &[],
            depth_scale_m: 0.001,
            rgb: &[],
        };
        assert_eq!(
            detect(&zero, &id, &cfg),
            Err(DetectError::InvalidIntrinsics)
        );
        let bad_cfg = DetectorConfig {
            voxel_size_m: 0.0,
            ..cfg
        };
        assert!(matches!(
            detect(&good, &id, &bad_cfg),
            Err(DetectError::InvalidConfig(_))
        ));
        let bad_range = DetectorConfig {
            min_depth_m: 2.0,
            max_depth_m: 1.0,
            ..cfg
        };
        assert!(matches!(
            detect(&good, &id, &bad_range),
            Err(DetectError::InvalidConfig(_))
        ));
    }

    #[test]
    fn matches_a_straightforward_reference_on_a_varied_frame() {
        use std::collections::BTreeMap;
        let k = CameraIntrinsics::from_horizontal_fov(40, 30, 80f64.to_radians());
        let depth: Vec<u16> = (0..1200u32)
            .map(|i| {
                if i % 17 == 0 {
                    0
                } else {
                    (400 + (i * 7919) % 2000) as u16
                }
            })
            .collect();
        let rgb: Vec<u8> = (0..3600u32)
            .map(|i| (i.wrapping_mul(2654435761) >> 24) as u8)
            .collect();
        let frame = mm_frame(k, &depth, &rgb);
        let pose = look_along(&Point3::new(-0.3, 0.4, 1.2), &Vector3::new(1.0, 0.5, -0.3));
        let config = DetectorConfig {
            voxel_size_m: 0.03,
            ..Default::default()
        };
        // The paper's way (mean colour per voxel) and the default (pixel votes), both checked.
        let cloud = detect_with(&frame, &pose, &config, &config.rule).unwrap();
        let voted = detect(&frame, &pose, &config).unwrap();
        assert_eq!(voted.points_in_world, cloud.points_in_world);

        // Per voxel: position sum, colour sums, pixels, pixels the rule accepts.
        type Sums = (Vector3<f64>, [u32; 3], u32, u32);
        let mut reference: BTreeMap<[i32; 3], Sums> = BTreeMap::new();
        let mut invalid = 0;
        for (i, &d) in depth.iter().enumerate() {
            let depth_m = d as f64 * 0.001;
            if d == 0 || !(0.15..=3.0).contains(&depth_m) {
                invalid += 1;
                continue;
            }
            let p = pose * k.backproject((i % 40) as f64, (i / 40) as f64, depth_m);
            let key = [p.x, p.y, p.z].map(|c| (c / 0.03).floor() as i32);
            let e = reference
                .entry(key)
                .or_insert((Vector3::zeros(), [0; 3], 0, 0));
            e.0 += p.coords;
            for a in 0..3 {
                e.1[a] += rgb[3 * i + a] as u32;
            }
            e.2 += 1;
            e.3 += u32::from(
                config
                    .rule
                    .is_roi(rgb[3 * i], rgb[3 * i + 1], rgb[3 * i + 2]),
            );
        }
        assert_eq!(cloud.invalid_pixels, invalid);
        assert_eq!(cloud.points_in_world.len(), reference.len());
        for ((((p, &roi), &voted_roi), rgb), (sum, colour, n, k)) in cloud
            .points_in_world
            .iter()
            .zip(&cloud.roi)
            .zip(&voted.roi)
            .zip(&cloud.rgb)
            .zip(reference.values())
        {
            let mean = sum / *n as f64;
            assert!((p.coords.cast::<f64>() - mean).norm() < 1e-5);
            let c = colour.map(|c| (c / n) as u8);
            assert_eq!(roi, config.rule.is_roi(c[0], c[1], c[2]));
            assert_eq!(*rgb, c, "the point's colour is its pixels' mean");
            assert_eq!(voted_roi, (*k as f32 + 1.0) / (*n as f32 + 3.0) >= 0.5);
        }
    }
}

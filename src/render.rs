//! `glasshouse render`: what the robot's camera sees, as two PNGs a person can look at.

use std::fs::File;
use std::io::BufWriter;
use std::path::{Path, PathBuf};
use std::time::Instant;

use anyhow::{bail, Context};
use glasshouse_geom::look_along;
use glasshouse_sim::{CameraModel, RgbdImage, ScenarioKind, Scene};
use nalgebra::{Isometry3, Point3, Vector3};

#[derive(clap::Args, Debug)]
pub struct RenderArgs {
    /// Simulated scenario: 1, 2 or row.
    #[arg(long, default_value = "1")]
    pub scenario: String,
    /// Scene seed.
    #[arg(long, default_value_t = 1)]
    pub seed: u64,
    #[command(flatten)]
    pub world: glasshouse_edge::WorldArgs,
    /// Camera pose `x,y,z,yaw,pitch` (metres in the world frame, z up; degrees: yaw about +z
    /// from +x, pitch up from the horizontal). Default: the scenario's initial camera pose.
    #[arg(long, value_name = "X,Y,Z,YAW,PITCH", allow_hyphen_values = true)]
    pub camera: Option<String>,
    /// Image width in pixels (height is 3/4 of it; the camera keeps its 80° horizontal view).
    #[arg(long, default_value_t = 640)]
    pub width: u32,
    /// Colour image to write; the colour-mapped depth goes beside it as `<stem>-depth.png`.
    #[arg(long, default_value = "frame.png")]
    pub out: PathBuf,
}

/// Parses `x,y,z,yaw_deg,pitch_deg` into a camera pose looking along yaw and pitch, image x
/// axis horizontal.
pub fn parse_camera(text: &str) -> anyhow::Result<Isometry3<f64>> {
    let values: Vec<f64> = text
        .split(',')
        .map(|v| v.trim().parse::<f64>())
        .collect::<Result<_, _>>()
        .with_context(|| format!("--camera {text:?}: expected five numbers x,y,z,yaw,pitch"))?;
    let [x, y, z, yaw_deg, pitch_deg] = values[..] else {
        bail!(
            "--camera {text:?}: expected five numbers x,y,z,yaw,pitch, got {}",
            values.len()
        );
    };
    if values.iter().any(|v| !v.is_finite()) {
        bail!("--camera {text:?}: every value must be finite");
    }
    let (yaw, pitch) = (yaw_deg.to_radians(), pitch_deg.to_radians());
    let forward = Vector3::new(
        pitch.cos() * yaw.cos(),
        pitch.cos() * yaw.sin(),
        pitch.sin(),
    );
    Ok(look_along(&Point3::new(x, y, z), &forward))
}

pub fn run(args: RenderArgs) -> anyhow::Result<()> {
    let kind: ScenarioKind = args.scenario.parse()?;
    if args.width < 4 || args.width > 4096 {
        bail!("--width {} is out of range 4..=4096", args.width);
    }
    let world = args.world.settings()?;
    let scene = Scene::generate_with(kind, args.seed, &world.scene);
    let world_from_camera = match &args.camera {
        Some(text) => parse_camera(text)?,
        None => scene.initial_camera_pose(),
    };
    let camera = CameraModel::with_resolution(args.width, args.width * 3 / 4);
    let started = Instant::now();
    // The camera sits where the hand-eye error puts it, not where the pose says.
    let truth = world_from_camera * world.pose.believed_camera_from_true(args.seed);
    let image = scene.render_with(&camera, &truth, args.seed, &world.perception);
    let render_ms = started.elapsed().as_secs_f64() * 1e3;

    let depth_path = depth_path_beside(&args.out);
    let (w, h) = (camera.intrinsics.width, camera.intrinsics.height);
    write_png(&args.out, w, h, &image.rgb)?;
    write_png(
        &depth_path,
        w,
        h,
        &depth_colours(&image, camera.max_range_m),
    )?;
    let valid = image.depth_m.iter().filter(|d| d.is_finite()).count();
    let t = world_from_camera.translation.vector;
    println!(
        "scenario {kind} seed {}: camera at ({:.2}, {:.2}, {:.2}) m, {w}x{h}, {valid} valid depth pixels, rendered in {render_ms:.1} ms",
        args.seed, t.x, t.y, t.z
    );
    println!("wrote {} and {}", args.out.display(), depth_path.display());
    Ok(())
}

fn depth_path_beside(colour: &Path) -> PathBuf {
    let stem = colour
        .file_stem()
        .map(|s| s.to_string_lossy().into_owned())
        .unwrap_or_else(|| "frame".into());
    colour.with_file_name(format!("{stem}-depth.png"))
}

/// Near is yellow, far is dark blue (a viridis-like ramp); invalid pixels are black.
fn depth_colours(image: &RgbdImage, max_range_m: f64) -> Vec<u8> {
    const RAMP: [[f32; 3]; 5] = [
        [253.0, 231.0, 37.0],
        [94.0, 201.0, 98.0],
        [33.0, 145.0, 140.0],
        [59.0, 82.0, 139.0],
        [68.0, 1.0, 84.0],
    ];
    let mut rgb = Vec::with_capacity(image.depth_m.len() * 3);
    for &d in &image.depth_m {
        if !d.is_finite() {
            rgb.extend_from_slice(&[0, 0, 0]);
            continue;
        }
        let s = (f64::from(d) / max_range_m).clamp(0.0, 1.0) as f32 * (RAMP.len() - 1) as f32;
        let i = (s.floor() as usize).min(RAMP.len() - 2);
        let f = s - i as f32;
        for (lo, hi) in RAMP[i].iter().zip(&RAMP[i + 1]) {
            rgb.push((lo * (1.0 - f) + hi * f).round() as u8);
        }
    }
    rgb
}

fn write_png(path: &Path, width: u32, height: u32, rgb: &[u8]) -> anyhow::Result<()> {
    let file = File::create(path).with_context(|| format!("cannot create {}", path.display()))?;
    let mut encoder = png::Encoder::new(BufWriter::new(file), width, height);
    encoder.set_color(png::ColorType::Rgb);
    encoder.set_depth(png::BitDepth::Eight);
    let mut writer = encoder
        .write_header()
        .with_context(|| format!("cannot write {}", path.display()))?;
    writer
        .write_image_data(rgb)
        .with_context(|| format!("cannot write {}", path.display()))?;
    writer
        .finish()
        .with_context(|| format!("cannot finish {}", path.display()))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn camera_flag_parses_and_rejects_bad_values() {
        let pose = parse_camera("1,2,0.5,90,0").expect("valid");
        assert!((pose.translation.vector - Vector3::new(1.0, 2.0, 0.5)).norm() < 1e-12);
        let forward = glasshouse_geom::optical_axis(&pose);
        assert!((forward - Vector3::y()).norm() < 1e-9, "{forward}");
        let down = parse_camera("0,0,1,0,-90").expect("straight down is valid");
        assert!((glasshouse_geom::optical_axis(&down) + Vector3::z()).norm() < 1e-9);
        assert!(parse_camera("1,2,3").is_err());
        assert!(parse_camera("1,2,3,4,x").is_err());
        assert!(parse_camera("1,2,NaN,0,0").is_err());
    }

    #[test]
    fn depth_path_sits_beside_the_colour_image() {
        assert_eq!(
            depth_path_beside(Path::new("out/frame.png")),
            PathBuf::from("out/frame-depth.png")
        );
    }
}

//! `glasshouse dataset`: simulator frames with per-pixel fruit labels from the renderer's hit
//! ids, as NumPy arrays, for training a learned detector (`scripts/train-detector`). Depth is
//! written as the detector receives it (millimetres, 0 = no depth), so a model may use it.

use std::fs;
use std::io::Write;
use std::path::{Path, PathBuf};

use anyhow::{bail, Context};
use glasshouse_geom::look_at;
use glasshouse_sim::{CameraModel, FruitColour, ScenarioKind, Scene, SceneOptions};
use nalgebra::{Isometry3, Point3, Vector3};
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;

/// Metres per unit of the written depth, as in the trolley's frames.
const DEPTH_SCALE_M: f64 = 0.001;

#[derive(clap::Args, Debug)]
pub struct DatasetArgs {
    /// Directory to write `rgb.npy` (N×H×W×3 u8), `depth.npy` (N×H×W u16, millimetres, 0 = no
    /// depth, as the detector receives it), `label.npy` (N×H×W u8, 1 = fruit) and `meta.json`
    /// into; created if missing.
    #[arg(long)]
    pub out: PathBuf,
    /// Number of frames.
    #[arg(long, default_value_t = 120)]
    pub frames: u32,
    /// Scenarios the frames cycle through (comma-separated: 1, 2, row).
    #[arg(long, default_value = "1,2,row")]
    pub scenarios: String,
    /// Fruit colours the frames alternate between (comma-separated: red, green, leaf-green);
    /// they override the world's fruit colour.
    #[arg(long, default_value = "red,green")]
    pub fruit_colours: String,
    /// First scene seed; each frame's scene seed is this plus the frame index divided by the
    /// number of scenario and colour combinations, so red and green twins share geometry.
    #[arg(long, default_value_t = 1000)]
    pub seed: u64,
    /// Image width in pixels (height is 3/4 of it).
    #[arg(long, default_value_t = 320)]
    pub width: u32,
    /// The simulated world the frames are rendered in (light, clutter, fruit shape, depth).
    #[command(flatten)]
    pub world: glasshouse_edge::WorldArgs,
}

/// One frame's scene and camera.
struct FrameSpec {
    scenario: ScenarioKind,
    fruit_colour: FruitColour,
    scene_seed: u64,
}

fn parse_list<T: std::str::FromStr>(flag: &str, text: &str) -> anyhow::Result<Vec<T>>
where
    T::Err: std::error::Error + Send + Sync + 'static,
{
    let items: Vec<T> = text
        .split(',')
        .map(|s| s.parse::<T>())
        .collect::<Result<_, _>>()
        .with_context(|| format!("{flag} {text:?}"))?;
    if items.is_empty() {
        bail!("{flag} needs at least one value");
    }
    Ok(items)
}

pub fn run(args: DatasetArgs) -> anyhow::Result<()> {
    let scenarios: Vec<ScenarioKind> = parse_list("--scenarios", &args.scenarios)?;
    let colours: Vec<FruitColour> = parse_list("--fruit-colours", &args.fruit_colours)?;
    let world = args.world.settings()?;
    if args.frames == 0 || args.frames > 10_000 {
        bail!("--frames {} is out of range 1..=10000", args.frames);
    }
    if !(16..=1280).contains(&args.width) {
        bail!("--width {} is out of range 16..=1280", args.width);
    }
    let camera = CameraModel::with_resolution(args.width, args.width * 3 / 4);
    let (width, height) = (camera.intrinsics.width, camera.intrinsics.height);
    let pixels = camera.intrinsics.pixel_count();
    let mut rgb = Vec::with_capacity(args.frames as usize * pixels * 3);
    let mut depth = Vec::with_capacity(args.frames as usize * pixels);
    let mut labels = Vec::with_capacity(args.frames as usize * pixels);
    let mut frame_colours = Vec::new();
    let mut fruit_pixels = 0usize;
    let progress = crate::progress::Progress::new("dataset", args.frames as u64);
    let combos = (scenarios.len() * colours.len()) as u64;
    for frame in 0..args.frames as u64 {
        let spec = FrameSpec {
            scenario: scenarios[(frame / colours.len() as u64) as usize % scenarios.len()],
            fruit_colour: colours[frame as usize % colours.len()],
            scene_seed: args.seed + frame / combos,
        };
        let options = SceneOptions {
            fruit_colour: spec.fruit_colour,
            ..world.scene
        };
        let scene = Scene::generate_with(spec.scenario, spec.scene_seed, &options);
        // Twins (same geometry, other colour) also share the view.
        let view_seed = args.seed ^ (frame / colours.len() as u64).wrapping_mul(0x9e37_79b9);
        let world_from_camera = random_view(&scene, view_seed);
        let image = scene.render_with(&camera, &world_from_camera, view_seed, &world.perception);
        let label = scene.fruit_label_image(&camera, &world_from_camera);
        fruit_pixels += label.iter().filter(|&&l| l == 1).count();
        rgb.extend_from_slice(&image.rgb);
        depth.extend(image.depth_as_u16(DEPTH_SCALE_M));
        labels.extend_from_slice(&label);
        frame_colours.push(spec.fruit_colour.to_string());
        progress.inc(1);
    }
    progress.finish_and_clear();
    let n = args.frames as usize;
    let shape_hw = [n, height as usize, width as usize];
    write_dataset(&args.out, &rgb, &depth, &labels, shape_hw)?;
    let meta = serde_json::json!({
        "frames": n, "width": width, "height": height, "seed": args.seed,
        "scenarios": args.scenarios, "fruit_colour": frame_colours,
        "fruit_pixel_share": fruit_pixels as f64 / labels.len().max(1) as f64,
        "depth_scale_m": DEPTH_SCALE_M, "world": world,
    });
    fs::write(
        args.out.join("meta.json"),
        serde_json::to_string_pretty(&meta)?,
    )?;
    println!(
        "wrote {n} frames of {width}x{height} to {} ({:.2} % fruit pixels)",
        args.out.display(),
        100.0 * fruit_pixels as f64 / labels.len().max(1) as f64
    );
    Ok(())
}

fn write_dataset(
    out: &Path,
    rgb: &[u8],
    depth: &[u16],
    labels: &[u8],
    [n, h, w]: [usize; 3],
) -> anyhow::Result<()> {
    fs::create_dir_all(out).with_context(|| format!("creating {}", out.display()))?;
    write_npy(&out.join("rgb.npy"), "|u1", &[n, h, w, 3], rgb)?;
    let depth_bytes: Vec<u8> = depth.iter().flat_map(|d| d.to_le_bytes()).collect();
    write_npy(&out.join("depth.npy"), "<u2", &[n, h, w], &depth_bytes)?;
    write_npy(&out.join("label.npy"), "|u1", &[n, h, w], labels)
}

/// A camera in a free spot of the workspace looking at a random fruit (or plant) with some
/// jitter, so frames show fruit at many sizes and partly hidden by leaves.
fn random_view(scene: &Scene, seed: u64) -> Isometry3<f64> {
    let mut rng = ChaCha8Rng::seed_from_u64(seed);
    let ws = scene.camera_workspace();
    let targets: Vec<Point3<f64>> = if scene.fruits().is_empty() {
        scene.plant_bases()
    } else {
        scene.fruits().iter().map(|f| f.centre).collect()
    };
    let Some(&first) = targets.first() else {
        return scene.initial_camera_pose();
    };
    for _ in 0..200 {
        let target = targets[rng.gen_range(0..targets.len())];
        let jitter = Vector3::from_fn(|_, _| rng.gen_range(-0.1..0.1));
        let distance_m = rng.gen_range(0.25..0.8);
        let direction = Vector3::new(
            rng.gen_range(-1.0..1.0),
            rng.gen_range(-1.0..1.0),
            rng.gen_range(-0.5..0.5),
        );
        let Some(direction) = direction.try_normalize(1e-9) else {
            continue;
        };
        let eye = target + direction * distance_m;
        if ws.contains(&eye) && scene.is_camera_position_free(&eye) {
            return look_at(&eye, &(target + jitter));
        }
    }
    look_at(
        &scene.initial_camera_pose().translation.vector.into(),
        &first,
    )
}

/// A NumPy `.npy` file (format 1.0) in C order; `descr` is the element type (`|u1`, `<u2`) and
/// `data` its bytes.
fn write_npy(path: &Path, descr: &str, shape: &[usize], data: &[u8]) -> anyhow::Result<()> {
    let dims: Vec<String> = shape.iter().map(|d| d.to_string()).collect();
    let shape_text = if dims.len() == 1 {
        format!("({},)", dims[0])
    } else {
        format!("({})", dims.join(", "))
    };
    let mut header =
        format!("{{'descr': '{descr}', 'fortran_order': False, 'shape': {shape_text}, }}");
    // Magic (6) + version (2) + length (2) + header + newline is padded to a multiple of 64.
    let unpadded = 10 + header.len() + 1;
    header.push_str(&" ".repeat((64 - unpadded % 64) % 64));
    header.push('\n');
    let mut file =
        fs::File::create(path).with_context(|| format!("creating {}", path.display()))?;
    file.write_all(b"\x93NUMPY\x01\x00")?;
    file.write_all(&(header.len() as u16).to_le_bytes())?;
    file.write_all(header.as_bytes())?;
    file.write_all(data)?;
    Ok(())
}

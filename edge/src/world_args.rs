//! The simulated world's flags, shared by `edge` and the `glasshouse` commands that simulate
//! (`demo`, `eval`, `render`, `dataset`): a preset, then one flag per imperfection.

use anyhow::Context;
use glasshouse_sim::{DepthNoiseModel, FruitColour, FruitShape, WorldPreset, WorldSettings};

/// How much the simulated glasshouse fights back. `--world realistic` turns every imperfection
/// on at a careful real set-up's values; each flag below overrides one part of the preset.
#[derive(clap::Args, Debug, Clone, Default)]
pub struct WorldArgs {
    /// The simulated world: `clean` (every imperfection off) or `realistic` (hand-eye error
    /// 0.5° + 5 mm, joint noise 0.05°, rail error 10 mm per segment, D435 depth, 1 px
    /// silhouette artefacts, specular dropouts, shadows, capsicum-shaped fruit, 1.5 % of
    /// leaves fruit-red plus clips, labels and red stems). Default: clean, or the settings
    /// file's world.
    #[arg(long, value_name = "WORLD")]
    pub world: Option<WorldPreset>,
    /// Hand-eye calibration error: camera rotation against its calibrated mount, degrees
    /// (random axis, fixed per trolley).
    #[arg(long, value_name = "DEG")]
    pub hand_eye_error_deg: Option<f64>,
    /// Hand-eye calibration error: camera offset against its calibrated mount, millimetres
    /// (random direction, fixed per trolley).
    #[arg(long, value_name = "MM")]
    pub hand_eye_error_mm: Option<f64>,
    /// Joint encoder noise per frame: standard deviation per joint, degrees.
    #[arg(long, value_name = "DEG")]
    pub joint_noise_deg: Option<f64>,
    /// Rail odometry error: standard deviation added at each segment along the row, mm.
    #[arg(long, value_name = "MM")]
    pub rail_error_mm: Option<f64>,
    /// Depth noise model: `paper` (i.i.d., 1.5 mm at 1 m) or `d435` (a stereo camera: RMS
    /// growing with range squared, correlated low-frequency error, smeared edges).
    #[arg(long, value_name = "MODEL")]
    pub depth_noise: Option<DepthNoiseModel>,
    /// Depth artefacts at plant silhouettes: band width in pixels where depth goes missing or
    /// mixes foreground and background (0 = none, at most 8).
    #[arg(long, value_name = "PX")]
    pub silhouette_px: Option<u32>,
    /// Depth dropouts on specular highlights of the fruit skin (true/false; bare flag = true).
    #[arg(long, value_name = "BOOL", num_args = 0..=1, default_missing_value = "true")]
    pub specular_dropouts: Option<bool>,
    /// Sun with shadows, sky shade under the canopy, highlights and exposure varying per frame
    /// (true/false; bare flag = true).
    #[arg(long, value_name = "BOOL", num_args = 0..=1, default_missing_value = "true")]
    pub shadows: Option<bool>,
    /// Detector label noise: probability in [0, 1] that each pixel's fruit/non-fruit label
    /// flips, independently per pixel and frame (0 = the perfect colour detector).
    #[arg(long, value_name = "P")]
    pub label_noise: Option<f64>,
    /// Persistent fruit-coloured things that are not fruit: share of leaves in [0, 0.2] that
    /// are fruit-red; above 0 also a red clip per plant, labels and red stems.
    #[arg(long, value_name = "SHARE")]
    pub red_clutter: Option<f64>,
    /// Fruit shape: `ellipsoid` (axis-aligned) or `capsicum` (lobed, tapered, tilted up to
    /// 30°, stalk and calyx, some pressed against leaves).
    #[arg(long, value_name = "SHAPE")]
    pub fruit_shape: Option<FruitShape>,
    /// Fruit colour: `red` (ripe, what the HSI rule finds), `green` (unripe, light
    /// yellow-green) or `leaf-green` (the leaves' own colour range).
    #[arg(long, value_name = "COLOUR")]
    pub fruit_colour: Option<FruitColour>,
    /// The scene on day D of a season of visits (0: the first visit; fruit swell, set and are
    /// harvested over the days, leaves drift and grow, every fruit keeps its id). Default: the
    /// scene as generated, which is no visit's.
    #[arg(long, value_name = "D")]
    pub day: Option<f64>,
}

impl WorldArgs {
    /// The world these flags ask for on top of `base` (the settings file's world, or the
    /// default clean one): the preset replaces it, then each flag given overrides its part.
    pub fn apply_to(&self, base: WorldSettings) -> anyhow::Result<WorldSettings> {
        let mut world = self.world.map_or(base, WorldSettings::preset);
        let set = |slot: &mut f64, flag: Option<f64>| {
            if let Some(v) = flag {
                *slot = v;
            }
        };
        set(&mut world.pose.hand_eye_error_deg, self.hand_eye_error_deg);
        set(&mut world.pose.hand_eye_error_mm, self.hand_eye_error_mm);
        set(&mut world.pose.joint_noise_deg, self.joint_noise_deg);
        set(&mut world.pose.rail_error_mm, self.rail_error_mm);
        set(&mut world.perception.label_noise, self.label_noise);
        set(&mut world.scene.red_clutter, self.red_clutter);
        let p = &mut world.perception;
        p.depth_noise = self.depth_noise.unwrap_or(p.depth_noise);
        p.silhouette_px = self.silhouette_px.unwrap_or(p.silhouette_px);
        p.specular_dropouts = self.specular_dropouts.unwrap_or(p.specular_dropouts);
        p.shadows = self.shadows.unwrap_or(p.shadows);
        let s = &mut world.scene;
        s.fruit_shape = self.fruit_shape.unwrap_or(s.fruit_shape);
        s.fruit_colour = self.fruit_colour.unwrap_or(s.fruit_colour);
        s.day = self.day.or(s.day);
        world
            .validate()
            .context("--world and the flags that override it")?;
        Ok(world)
    }

    /// The world of these flags on top of the clean default.
    pub fn settings(&self) -> anyhow::Result<WorldSettings> {
        self.apply_to(WorldSettings::default())
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use clap::Parser;

    #[derive(Parser)]
    struct Cli {
        #[command(flatten)]
        world: WorldArgs,
    }

    fn parse(args: &[&str]) -> anyhow::Result<WorldSettings> {
        let cli = Cli::try_parse_from(std::iter::once("t").chain(args.iter().copied()))?;
        cli.world.settings()
    }

    #[test]
    fn the_preset_is_taken_then_flags_override_it() -> anyhow::Result<()> {
        assert_eq!(parse(&[])?, WorldSettings::default());
        assert_eq!(
            parse(&["--world", "realistic"])?,
            WorldSettings::realistic()
        );
        let doubled = parse(&[
            "--world",
            "realistic",
            "--hand-eye-error-deg",
            "1",
            "--hand-eye-error-mm",
            "10",
            "--shadows",
            "false",
        ])?;
        assert_eq!(doubled.pose.hand_eye_error_deg, 1.0);
        assert_eq!(doubled.pose.hand_eye_error_mm, 10.0);
        assert!(!doubled.perception.shadows);
        assert_eq!(doubled.scene, WorldSettings::realistic().scene);
        let bare = parse(&["--shadows", "--fruit-colour", "leaf-green"])?;
        assert!(bare.perception.shadows);
        assert_eq!(bare.scene.fruit_colour, FruitColour::LeafGreen);
        Ok(())
    }

    #[test]
    fn out_of_range_flags_are_errors_that_name_the_setting() {
        let err = parse(&["--joint-noise-deg=-1"]).expect_err("negative noise");
        assert!(format!("{err:#}").contains("joint noise"), "{err:#}");
        let err = parse(&["--silhouette-px", "9"]).expect_err("too wide");
        assert!(format!("{err:#}").contains("silhouette"), "{err:#}");
        assert!(parse(&["--depth-noise", "kinect"]).is_err());
    }
}

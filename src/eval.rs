//! `glasshouse eval`: the paper's experiments (Table I, Fig. 5 and 6) on the simulator.
//!
//! Runs `--trials` seeded trials per method through [`glasshouse_eval::Trial`] (the services'
//! detector and planner code on the simulated clock), in parallel on `--jobs` threads, and writes
//! into `--out`:
//!
//! - `trials/<method>-<trial>.csv`: the metrics at every simulated second;
//! - `trials/<method>-<trial>-fruits.csv`: the final estimates against the true fruits, a row
//!   per true fruit and per false fruit (fitted and box centre distance and volume accuracy);
//! - `trials/<method>-<trial>-clusters.csv`: every ROI cluster at the end, reported as a fruit
//!   or not and why (the fruit evidence's verdict, its shape, what its fitted solid hides), with
//!   the nearest true fruit, and whether it is reported for the fruit body found under it
//!   (`body`);
//! - `trials/<method>-<trial>-views.csv`: the best view of every plan, when it was planned,
//!   its list (ROI or exploration), scores and predicted motion time, and the fruits detected
//!   then (`scripts/view-yield OUT` sums what each list's views cost and find);
//! - `table.md`: Table I (mean ± std at the end of the budget), the missed fruits by reason and
//!   the Mann-Whitney p-values;
//! - `summary.json`: `{"<method>": {"<metric>": {"mean", "std", "n"}}, "fruits_total", "p_values",
//!   "settings"}`;
//! - `covered_volume.png`, `volume_accuracy.png`, `f1.png`, `count_ratio.png`: mean curves over
//!   time per method.
//!
//! `--label-noise P` and `--silhouette-px N` put the simulated detector's errors into every
//! frame (per-pixel label flips, depth artefacts at plant silhouettes), seeded per frame.
//!
//! Trial `t` (from 0) uses seed `--seed + t` for the scene, the camera noise and the planner, the
//! same for every method, so methods are compared on the same scenes; `glasshouse demo --seed`
//! with that seed shows the same scene.

use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicUsize, Ordering};
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};

use anyhow::{bail, ensure, Context};
use glasshouse_detect::FruitDetector;
use glasshouse_eval::plot::{render_png, PlotSpec, Series, PALETTE};
use glasshouse_eval::report::{self, method_label, MethodRuns};
use glasshouse_eval::{ComputeTime, Trial, TrialConfig, TrialResult};
use glasshouse_eval::{RoiEvidence, RoiTargets};
use glasshouse_nbv::Method;
use glasshouse_roimap::{PriorRules, RoiMap};
use glasshouse_sim::{ScenarioKind, WorldSettings};
use indicatif::ProgressStyle;

use crate::progress::Progress;

mod visits;

/// The simulated world and the detector (`demo` and `eval`).
#[derive(clap::Args, Debug, Clone, Default)]
pub struct PerceptionArgs {
    #[command(flatten)]
    pub world: glasshouse_edge::WorldArgs,
    /// Label fruit with this ONNX segmentation model (detector-service/model/) instead of
    /// the HSI colour rule.
    #[arg(long, value_name = "FILE")]
    pub fruit_model: Option<PathBuf>,
}

impl PerceptionArgs {
    /// The world these flags ask for, or an error naming the setting out of range.
    pub fn world(&self) -> anyhow::Result<WorldSettings> {
        self.world.settings()
    }

    /// The detector these flags ask for: the model of --fruit-model, else the HSI rule.
    pub fn fruit_detector(&self) -> anyhow::Result<Arc<dyn FruitDetector>> {
        let model = self.fruit_model.as_deref();
        glasshouse_detector::load_fruit_detector(model)
            .with_context(|| format!("--fruit-model {}", model.unwrap_or(Path::new("")).display()))
    }
}

#[derive(clap::Args, Debug)]
pub struct EvalArgs {
    /// Simulated scenario: 1, 2 or row.
    #[arg(long, default_value = "2")]
    pub scenario: ScenarioKind,
    /// Comma-separated methods: ours-uu, ours-up, explo-uu, explo-up.
    #[arg(
        long,
        value_delimiter = ',',
        default_value = "ours-uu,ours-up,explo-uu,explo-up"
    )]
    pub methods: Vec<Method>,
    /// Trials per method.
    #[arg(long, default_value_t = 20)]
    pub trials: u32,
    /// Simulated seconds per trial.
    #[arg(long, default_value_t = 180.0)]
    pub budget_s: f64,
    /// Seed of trial 0; trial t uses seed + t.
    #[arg(long, default_value_t = 1)]
    pub seed: u64,
    /// Output directory (created if missing).
    #[arg(long)]
    pub out: PathBuf,
    /// Charge this fixed planner compute time per view instead of the measured one, so that a
    /// run replays bit for bit.
    #[arg(long, value_name = "MS")]
    pub compute_ms: Option<f64>,
    /// Image width in pixels (height is 3/4 of it); smaller runs faster.
    #[arg(long, default_value_t = 640)]
    pub width: u32,
    /// Trials run in parallel (default: the number of cores).
    #[arg(long)]
    pub jobs: Option<usize>,
    /// How detections enter the ROI map: `labels` (full-strength labels, the planner's default)
    /// or `confidence` (each voxel's detection confidence as its log-odds, capped).
    #[arg(long, value_name = "HOW", default_value_t = RoiEvidence::Labels)]
    pub roi_evidence: RoiEvidence,
    /// Which ROI voxels ROI-targeted sampling aims at: `patches` (those with an ROI face
    /// neighbour, the planner's default) or `every` (the paper).
    #[arg(long, value_name = "WHICH", default_value_t = RoiTargets::Patches)]
    pub roi_targets: RoiTargets,
    /// Align each scan to the map before inserting it (point-to-plane ICP, checked; off by
    /// default, as in the planner), for a side-by-side run.
    #[arg(long)]
    pub registration: bool,
    /// Do not estimate the trolley's hand-eye calibration error (the planner's default
    /// estimates it across its first scans and undoes it before each scan goes into the map),
    /// for a side-by-side run.
    #[arg(long)]
    pub no_hand_eye: bool,
    /// Integrate each cloud's rays up to this range, metres (the planner's `max_range_m`;
    /// points further away free their ray up to it and mark nothing), for a side-by-side run.
    #[arg(long, value_name = "M", default_value_t = glasshouse_pipeline::PlanningSettings::default().max_range_m)]
    pub max_range: f64,
    /// Points beyond the range free one ray per voxel at the range instead of one each (the
    /// planner's `merge_far_rays`), for a side-by-side run.
    #[arg(long, value_name = "BOOL", action = clap::ArgAction::Set, default_value_t = glasshouse_pipeline::PlanningSettings::default().merge_far_rays)]
    pub merge_far_rays: bool,
    /// Draw ROI targets nearer the camera more often, weight `exp(−distance / M)` (the
    /// planner's `roi_target_near_m`; 0, the default, draws them uniformly as the paper), for a
    /// side-by-side run.
    #[arg(long, value_name = "M", default_value_t = glasshouse_pipeline::PlanningSettings::default().roi_target_near_m)]
    pub roi_target_near: f64,
    /// Rank views by utility less this much per second the robot takes to reach them (the
    /// planner's default); 0 ranks by the paper's utility alone, for a side-by-side run.
    #[arg(long, value_name = "W", default_value_t = glasshouse_pipeline::DEFAULT_COST_WEIGHT_PER_S)]
    pub motion_cost_per_s: f64,
    /// A cluster shaped like no fruit (flat, thin, too small) once scans from this many
    /// directions hit it stops drawing ROI-targeted views, for a side-by-side run; 0 (the
    /// planner's default) keeps every cluster a target, as in the paper.
    #[arg(long, value_name = "N", default_value_t = glasshouse_pipeline::DEFAULT_CLUTTER_SETTLES_AFTER_VIEWS)]
    pub clutter_settles_after: u32,
    /// A cluster taken for a fruit, once scans from this many distinct directions hit it, stops
    /// drawing ROI-targeted views (its hidden back), for a side-by-side run; 0 (the planner's
    /// default) keeps every found fruit a target, as in the paper.
    #[arg(long, value_name = "N", default_value_t = glasshouse_pipeline::DEFAULT_FRUIT_SETTLES_AFTER_VIEWS)]
    pub fruit_settles_after: u32,
    /// Once this many clouds in a row bring no new fruit-shaped cluster, plans take the
    /// exploration views whenever one beats the threshold (the ROI targets left are found
    /// fruits' hidden backs and clutter); 0: the paper's choice between the lists, for a
    /// side-by-side run.
    #[arg(long, value_name = "N", default_value_t = glasshouse_pipeline::DEFAULT_EXPLORE_AFTER_FRUITLESS_CLOUDS)]
    pub explore_after_fruitless: u32,
    /// Tries of ROI-targeted sampling drawn until 100 candidates survive the workspace,
    /// occlusion and reach checks; 0: 100 tries, as the paper, for a side-by-side run.
    #[arg(long, value_name = "N", default_value_t = glasshouse_pipeline::DEFAULT_ROI_TRIES)]
    pub roi_tries: usize,
    /// Report only the ROI clusters the shape rule and the inside test pass: no search for a
    /// fruit's body in the occupancy map under the patches they turn away (a leaf-coloured
    /// fruit in shade is labelled only in patches), for a side-by-side run.
    #[arg(long)]
    pub no_body_search: bool,
    /// A voxel above this occupancy log-odds between an ROI target and a candidate camera
    /// drops the candidate as occluded; the default is the paper's p > 0.6 (0.405), which a
    /// single hit passes, for a side-by-side run.
    #[arg(long, value_name = "L", default_value_t = glasshouse_pipeline::PlanningSettings::default().occlusion_occupancy_logodds)]
    pub occlusion_logodds: f32,
    /// Fitted solids are shrunk by F · voxel² / R on every semi-axis (R the geometric mean of
    /// their semi-axes): the voxels a convex fruit's surface passes through have their centres
    /// outside it on average, so a solid through them is too large; 0 fits through the voxel
    /// centres, for a side-by-side run.
    #[arg(long, value_name = "F", default_value_t = glasshouse_pipeline::PlanningSettings::default().fit.voxel_bias_factor)]
    pub voxel_bias_factor: f64,
    /// Visit every trial's scene over a season: on days 0, D, 2D, ... up to this day (D:
    /// `--visit-every-days`), one trial per visit, the scene grown between them (fruit swell,
    /// set and are harvested, leaves move), and each fruit followed from visit to visit. Writes
    /// visits.md (per visit, identity against the simulator's ids, growth error, revisit time)
    /// and visits.json instead of the single-visit tables.
    #[arg(long, value_name = "N")]
    pub days: Option<f64>,
    /// Days between two visits of `--days`.
    #[arg(long, default_value_t = 3.5, value_name = "D")]
    pub visit_every_days: f64,
    /// With `--days`: start every revisit from an empty map, not from the previous visit's
    /// map made into a prior (what was free stays likely free, the fruit are looked for again),
    /// to compare the two.
    #[arg(long)]
    pub revisit_from_empty: bool,
    /// With `--days`: how far below the ROI threshold (log-odds, > 0) a revisit's prior keeps
    /// the previous visit's fruit voxels; 0.05 (the default) makes one observation of fruit a
    /// fruit again, above the ROI hit (0.85) two are needed, as in a new map.
    #[arg(long, value_name = "LOGODDS", default_value_t = PriorRules::default().fruit_below_threshold_logodds)]
    pub prior_fruit_below: f32,
    /// With `--days`: the share (0 to 1) of the log-odds of the previous visit's free voxels a
    /// revisit's prior keeps (0, the default: none; the free voxels beside a fruit never).
    #[arg(long, value_name = "SHARE", default_value_t = PriorRules::default().free_share)]
    pub prior_free_share: f32,
    /// With `--days`: plan a revisit without aiming at the previous visit's fruit (the prior's
    /// hints only), to compare.
    #[arg(long)]
    pub no_revisit_aim: bool,
    #[command(flatten)]
    pub perception: PerceptionArgs,
}

/// Parsed and checked arguments.
struct Plan {
    scenario: ScenarioKind,
    methods: Vec<Method>,
    compute_time: ComputeTime,
    jobs: usize,
    world: WorldSettings,
    fruit_detector: Arc<dyn FruitDetector>,
}

fn check(args: &EvalArgs) -> anyhow::Result<Plan> {
    let mut methods = Vec::new();
    for &method in &args.methods {
        ensure!(
            !methods.contains(&method),
            "--methods: {method} given twice"
        );
        methods.push(method);
    }
    ensure!(!methods.is_empty(), "--methods: no method given");
    ensure!(args.trials > 0, "--trials must be at least 1");
    ensure!(
        args.budget_s.is_finite() && args.budget_s > 0.0 && args.budget_s <= 86_400.0,
        "--budget-s must be in (0, 86400]"
    );
    let compute_time = match args.compute_ms {
        Some(ms) => {
            ensure!(
                ms.is_finite() && ms >= 0.0,
                "--compute-ms must be finite and >= 0"
            );
            ComputeTime::Fixed { ms }
        }
        None => ComputeTime::Measured,
    };
    ensure!(
        (16..=1280).contains(&args.width),
        "--width must be within 16..=1280"
    );
    ensure!(
        args.max_range.is_finite() && args.max_range > 0.0,
        "--max-range must be finite and > 0 (metres), as the planner's max_range_m"
    );
    let cores = std::thread::available_parallelism().map_or(1, |n| n.get());
    let jobs = args.jobs.unwrap_or(cores);
    ensure!(jobs > 0, "--jobs must be at least 1");
    Ok(Plan {
        scenario: args.scenario,
        methods,
        compute_time,
        jobs,
        world: args.perception.world()?,
        fruit_detector: args.perception.fruit_detector()?,
    })
}

fn write(path: &Path, bytes: impl AsRef<[u8]>) -> anyhow::Result<()> {
    std::fs::write(path, bytes).with_context(|| format!("cannot write {}", path.display()))
}

/// Runs the experiment; see the module docs.
pub fn run(args: EvalArgs) -> anyhow::Result<()> {
    let plan = check(&args)?;
    if let Some(days) = args.days {
        let days = visits::visit_days(days, args.visit_every_days)?;
        return visits::run(&args, &plan, &days);
    }
    let trials_dir = prepare_out(&args.out)?;
    let height = args.width * 3 / 4;
    let configs = trial_configs(&args, &plan, height)?;
    let started = Instant::now();
    let results = run_trials(&configs, &plan, args.budget_s, Season::NONE)?;
    let (runs, wall_times) = group_by_method(&plan, &configs, results)?;
    let wall_s = started.elapsed().as_secs_f64();

    // Outputs.
    for run in &runs {
        for (t, result) in run.trials.iter().enumerate() {
            let path = trials_dir.join(format!("{}-{t}.csv", run.method));
            write(&path, report::trial_csv(result))?;
            let path = trials_dir.join(format!("{}-{t}-fruits.csv", run.method));
            write(&path, report::fruits_csv(result))?;
            let path = trials_dir.join(format!("{}-{t}-clusters.csv", run.method));
            write(&path, report::clusters_csv(result))?;
            let path = trials_dir.join(format!("{}-{t}-views.csv", run.method));
            write(&path, report::best_views_csv(result))?;
            let path = trials_dir.join(format!("{}-{t}-registration.json", run.method));
            write(&path, serde_json::to_string_pretty(&result.registration)?)?;
        }
        print_registration(run);
    }
    let mut table = report::table_markdown(&plan.scenario.to_string(), &runs, args.budget_s);
    table.push_str(&plot_notes(&runs));
    write(&args.out.join("table.md"), &table)?;
    let settings = serde_json::json!({
        "scenario": plan.scenario.to_string(),
        "methods": plan.methods.iter().map(|m| m.to_string()).collect::<Vec<_>>(),
        "trials": args.trials,
        "budget_s": args.budget_s,
        "seed": args.seed,
        "compute_ms": args.compute_ms,
        "motion": "arm",
        "width": args.width,
        "height": height,
        "world": plan.world,
        "roi_evidence": args.roi_evidence,
        "roi_targets": args.roi_targets,
        "registration": args.registration,
        "hand_eye": !args.no_hand_eye,
        "motion_cost_per_s": args.motion_cost_per_s,
        "roi_target_near_m": args.roi_target_near,
        "clutter_settles_after": args.clutter_settles_after,
        "fruit_settles_after": args.fruit_settles_after,
        "explore_after_fruitless": args.explore_after_fruitless,
        "roi_tries": args.roi_tries,
        "body_search": !args.no_body_search,
        "occlusion_logodds": args.occlusion_logodds,
        "voxel_bias_factor": args.voxel_bias_factor,
        "detector": plan.fruit_detector.name(),
        "fruit_model": args.perception.fruit_model,
    });
    let summary = report::summary_json(&runs, settings);
    write(
        &args.out.join("summary.json"),
        serde_json::to_string_pretty(&summary)?,
    )?;
    write_plots(&args.out, &runs, args.budget_s)?;

    let mean_trial_s = wall_times.iter().sum::<f64>() / wall_times.len().max(1) as f64;
    println!(
        "glasshouse eval: {} trials in {:.1} s wall ({:.1} s per trial on average, {} jobs); \
         results in {}",
        configs.len(),
        wall_s,
        mean_trial_s,
        plan.jobs,
        args.out.display()
    );
    print!("{table}");
    Ok(())
}

/// One line per method: how the registrations of all its trials' clouds ended.
fn print_registration(run: &MethodRuns) {
    let mut total = glasshouse_pipeline::AlignmentCounts::default();
    for trial in &run.trials {
        total += trial.registration;
    }
    let counts = serde_json::to_string(&total).unwrap_or_default();
    println!("{}: registration of every cloud: {counts}", run.method);
}

/// Creates `out/trials` and checks `out` is writable, so an unusable output directory fails
/// before hours of simulation.
fn prepare_out(out: &Path) -> anyhow::Result<PathBuf> {
    let trials_dir = out.join("trials");
    std::fs::create_dir_all(&trials_dir)
        .with_context(|| format!("cannot create {}", trials_dir.display()))?;
    let probe = out.join(".write-test");
    write(&probe, b"")?;
    let _ = std::fs::remove_file(&probe);
    Ok(trials_dir)
}

/// Every trial of every method, method by method; trial `t` uses seed `--seed + t`.
fn trial_configs(args: &EvalArgs, plan: &Plan, height: u32) -> anyhow::Result<Vec<TrialConfig>> {
    let configs: Vec<TrialConfig> = plan
        .methods
        .iter()
        .flat_map(|&method| {
            (0..args.trials).map(move |t| TrialConfig {
                width: args.width,
                height,
                budget_s: args.budget_s,
                compute_time: plan.compute_time,
                world: plan.world,
                roi_evidence: args.roi_evidence,
                roi_targets: args.roi_targets,
                registration: args.registration,
                hand_eye: !args.no_hand_eye,
                motion_cost_per_s: args.motion_cost_per_s,
                clutter_settles_after_views: args.clutter_settles_after,
                fruit_settles_after_views: args.fruit_settles_after,
                explore_after_fruitless_clouds: args.explore_after_fruitless,
                roi_tries: args.roi_tries,
                body_search: !args.no_body_search,
                occlusion_occupancy_logodds: args.occlusion_logodds,
                voxel_bias_factor: args.voxel_bias_factor,
                revisit_aim: !args.no_revisit_aim,
                max_range_m: args.max_range,
                merge_far_rays: args.merge_far_rays,
                roi_target_near_m: args.roi_target_near,
                ..TrialConfig::new(plan.scenario, method, args.seed.wrapping_add(u64::from(t)))
            })
        })
        .collect();
    for config in &configs {
        config.validate()?;
    }
    Ok(configs)
}

/// What the trial threads share: the next trial to take, the results and the first error.
struct TrialQueue<'a> {
    configs: &'a [TrialConfig],
    /// A thread takes this many consecutive configs at once and runs them in turn (a season's
    /// visits), each after the first from its predecessor's map made into a prior when
    /// `prior` is set.
    season: Season,
    fruit_detector: Arc<dyn FruitDetector>,
    next: AtomicUsize,
    done: AtomicUsize,
    results: Mutex<Vec<Option<(TrialResult, f64)>>>,
    first_error: Mutex<Option<anyhow::Error>>,
    bar: Progress,
}

/// How consecutive trials belong together: one trial each (`visits: 1`), or a season's visits.
#[derive(Clone, Copy, Debug)]
struct Season {
    visits: usize,
    prior: Option<PriorRules>,
}

impl Season {
    const NONE: Season = Season {
        visits: 1,
        prior: None,
    };
}

/// Runs the trials on `jobs` threads; returns (result, wall seconds) per config, in order.
fn run_trials(
    configs: &[TrialConfig],
    plan: &Plan,
    budget_s: f64,
    season: Season,
) -> anyhow::Result<Vec<Option<(TrialResult, f64)>>> {
    // Progress in simulated seconds over all trials; the message counts finished trials.
    let total_s = budget_s * configs.len() as f64;
    let bar = Progress::new("eval", (total_s * 10.0).round() as u64).with_style(
        ProgressStyle::with_template(
            "{bar:40} {msg} done, {elapsed_precise} elapsed, {eta_precise} left",
        )
        .context("progress bar template")?,
    );
    bar.set_message(format!("0/{} trials", configs.len()));
    bar.enable_steady_tick(Duration::from_millis(500));
    let jobs = plan.jobs;
    let queue = TrialQueue {
        configs,
        season,
        fruit_detector: plan.fruit_detector.clone(),
        next: AtomicUsize::new(0),
        done: AtomicUsize::new(0),
        results: Mutex::new((0..configs.len()).map(|_| None).collect()),
        first_error: Mutex::new(None),
        bar,
    };
    std::thread::scope(|scope| {
        for _ in 0..jobs.min(configs.len().div_ceil(season.visits.max(1))) {
            scope.spawn(|| queue.work());
        }
    });
    queue.bar.finish_and_clear();
    if let Some(e) = queue
        .first_error
        .into_inner()
        .map_err(|_| anyhow::anyhow!("a trial thread panicked"))?
    {
        return Err(e);
    }
    queue
        .results
        .into_inner()
        .map_err(|_| anyhow::anyhow!("a trial thread panicked"))
}

impl TrialQueue<'_> {
    /// One thread: takes seasons (single trials unless the queue's season says otherwise)
    /// until none is left or one has failed.
    fn work(&self) {
        let visits = self.season.visits.max(1);
        loop {
            let first = self.next.fetch_add(1, Ordering::Relaxed) * visits;
            if first >= self.configs.len() {
                break;
            }
            let mut prior = None;
            for index in first..(first + visits).min(self.configs.len()) {
                if self.first_error.lock().map(|e| e.is_some()).unwrap_or(true) {
                    return;
                }
                match self.run_one(index, prior.take()) {
                    Ok(map) => prior = self.season.prior.map(|rules| map.prior(&rules)),
                    Err(e) => {
                        if let Ok(mut slot) = self.first_error.lock() {
                            slot.get_or_insert(e);
                        }
                        return;
                    }
                }
            }
        }
    }

    /// Runs config `index` (from `prior` when given), stores its result; returns its final map.
    fn run_one(&self, index: usize, prior: Option<RoiMap>) -> anyhow::Result<RoiMap> {
        let config = self.configs[index];
        let failed = || format!("trial {} seed {} failed", config.method, config.seed);
        let trial_started = Instant::now();
        let mut reported = 0.0;
        let mut trial = Trial::new(config)
            .with_context(failed)?
            .with_fruit_detector(self.fruit_detector.clone());
        if let Some(prior) = prior {
            trial = trial.with_prior(prior).with_context(failed)?;
        }
        let (result, map) = trial
            .run_keeping_map(|clock_s| {
                let step = ((clock_s - reported) * 10.0).max(0.0);
                self.bar.inc(step.round() as u64);
                reported += step.round() / 10.0;
            })
            .with_context(failed)?;
        let wall_s = trial_started.elapsed().as_secs_f64();
        if let Ok(mut r) = self.results.lock() {
            r[index] = Some((result, wall_s));
        }
        let n = self.done.fetch_add(1, Ordering::Relaxed) + 1;
        self.bar
            .set_message(format!("{n}/{} trials", self.configs.len()));
        Ok(map)
    }
}

/// The trials of each method, and every trial's wall time.
fn group_by_method(
    plan: &Plan,
    configs: &[TrialConfig],
    results: Vec<Option<(TrialResult, f64)>>,
) -> anyhow::Result<(Vec<MethodRuns>, Vec<f64>)> {
    let mut runs: Vec<MethodRuns> = plan
        .methods
        .iter()
        .map(|&method| MethodRuns {
            method,
            trials: Vec::new(),
        })
        .collect();
    let mut wall_times = Vec::new();
    for (config, result) in configs.iter().zip(results) {
        let Some((result, wall_s)) = result else {
            bail!(
                "trial {} seed {} did not finish",
                config.method,
                config.seed
            );
        };
        wall_times.push(wall_s);
        if let Some(run) = runs.iter_mut().find(|r| r.method == config.method) {
            run.trials.push(result);
        }
    }
    Ok((runs, wall_times))
}

/// The legend of the plots in words (the PNGs carry it in colour).
fn plot_notes(runs: &[MethodRuns]) -> String {
    let mut out = String::from(
        "\n## Plots\n\n`covered_volume.png` (paper Fig. 5) and `volume_accuracy.png` (Fig. 6): \
         x = simulated time in s, y = the mean over trials at each second. Solid lines: box \
         estimates (the paper's); dashed: fitted ellipsoid estimates. Volume accuracy keeps \
         pairs with accuracy > 0.5 (the published plots' rule). `f1.png` and `count_ratio.png` \
         follow the fruit counts the same way (count ratio above 1: the map reports more fruit \
         than there is).\n\n",
    );
    for (i, run) in runs.iter().enumerate() {
        let [r, g, b] = PALETTE[i % PALETTE.len()];
        out.push_str(&format!(
            "- {} ({}): colour #{r:02x}{g:02x}{b:02x}\n",
            method_label(run.method),
            run.method
        ));
    }
    out
}

fn write_plots(out: &Path, runs: &[MethodRuns], budget_s: f64) -> anyhow::Result<()> {
    type Value = fn(&glasshouse_eval::Sample) -> f64;
    let plots: [(&str, &str, &str, Value, Value); 4] = [
        (
            "covered_volume.png",
            "covered roi volume",
            "covered share",
            |s| s.boxes.covered_volume,
            |s| s.fitted.covered_volume,
        ),
        (
            "volume_accuracy.png",
            "volume accuracy (pairs > 0.5)",
            "volume accuracy",
            |s| s.boxes.volume_accuracy_gt05,
            |s| s.fitted.volume_accuracy_gt05,
        ),
        (
            "f1.png",
            "fruit f1 (matched fruits)",
            "f1",
            |s| s.boxes.counts.f1,
            |s| s.fitted.counts.f1,
        ),
        (
            "count_ratio.png",
            "count ratio (reported / true fruits)",
            "count ratio",
            |s| s.boxes.counts.count_ratio,
            |s| s.fitted.counts.count_ratio,
        ),
    ];
    for (file, title, y_label, boxes, fitted) in plots {
        let mut series = Vec::new();
        for (i, run) in runs.iter().enumerate() {
            let color = PALETTE[i % PALETTE.len()];
            for (value, dashed, suffix) in [(boxes, false, ""), (fitted, true, " fit")] {
                let curve = report::mean_curve(&run.trials, value);
                series.push(Series {
                    label: format!("{}{suffix}", run.method),
                    color,
                    dashed,
                    points: curve
                        .iter()
                        .enumerate()
                        .map(|(t, v)| (t as f64, *v))
                        .collect(),
                });
            }
        }
        // Shares end at 1; a count ratio may exceed it (over-counting), so its axis grows.
        let highest = series
            .iter()
            .flat_map(|s| s.points.iter().map(|p| p.1))
            .filter(|y| y.is_finite())
            .fold(1.0, f64::max);
        let spec = PlotSpec {
            title: title.to_string(),
            x_label: "time (s)".to_string(),
            y_label: y_label.to_string(),
            x_max: budget_s,
            y_min: 0.0,
            y_max: highest.ceil(),
            width: 900,
            height: 560,
        };
        let png = render_png(&spec, &series)?;
        write(&out.join(file), png)?;
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    #![allow(clippy::unwrap_used)]

    use super::*;

    fn args(out: PathBuf) -> EvalArgs {
        EvalArgs {
            scenario: ScenarioKind::Two,
            methods: vec![Method::OursUu, Method::ExploUu],
            trials: 1,
            budget_s: 4.0,
            seed: 1,
            out,
            compute_ms: Some(50.0),
            width: 64,
            jobs: Some(2),
            roi_evidence: RoiEvidence::Labels,
            roi_targets: RoiTargets::Patches,
            registration: false,
            no_hand_eye: false,
            motion_cost_per_s: glasshouse_pipeline::DEFAULT_COST_WEIGHT_PER_S,
            max_range: glasshouse_pipeline::PlanningSettings::default().max_range_m,
            merge_far_rays: glasshouse_pipeline::PlanningSettings::default().merge_far_rays,
            roi_target_near: glasshouse_pipeline::PlanningSettings::default().roi_target_near_m,
            clutter_settles_after: glasshouse_pipeline::DEFAULT_CLUTTER_SETTLES_AFTER_VIEWS,
            fruit_settles_after: glasshouse_pipeline::DEFAULT_FRUIT_SETTLES_AFTER_VIEWS,
            explore_after_fruitless: glasshouse_pipeline::DEFAULT_EXPLORE_AFTER_FRUITLESS_CLOUDS,
            roi_tries: glasshouse_pipeline::DEFAULT_ROI_TRIES,
            no_body_search: false,
            occlusion_logodds: glasshouse_pipeline::PlanningSettings::default()
                .occlusion_occupancy_logodds,
            voxel_bias_factor: glasshouse_pipeline::PlanningSettings::default()
                .fit
                .voxel_bias_factor,
            days: None,
            visit_every_days: 3.5,
            revisit_from_empty: false,
            prior_fruit_below: PriorRules::default().fruit_below_threshold_logodds,
            prior_free_share: PriorRules::default().free_share,
            no_revisit_aim: false,
            perception: PerceptionArgs::default(),
        }
    }

    #[test]
    fn bad_input_is_an_error_not_a_panic() {
        let out = std::env::temp_dir().join(format!("gh-eval-bad-{}", std::process::id()));
        let bad = [
            EvalArgs {
                methods: Vec::new(),
                ..args(out.clone())
            },
            EvalArgs {
                methods: vec![Method::OursUu, Method::OursUu],
                ..args(out.clone())
            },
            EvalArgs {
                trials: 0,
                ..args(out.clone())
            },
            EvalArgs {
                budget_s: -1.0,
                ..args(out.clone())
            },
            EvalArgs {
                compute_ms: Some(f64::NAN),
                ..args(out.clone())
            },
            EvalArgs {
                jobs: Some(0),
                ..args(out.clone())
            },
            EvalArgs {
                max_range: 0.0,
                ..args(out.clone())
            },
            EvalArgs {
                perception: PerceptionArgs {
                    world: glasshouse_edge::WorldArgs {
                        label_noise: Some(1.5),
                        ..Default::default()
                    },
                    ..PerceptionArgs::default()
                },
                ..args(out.clone())
            },
            EvalArgs {
                perception: PerceptionArgs {
                    world: glasshouse_edge::WorldArgs {
                        label_noise: Some(0.3),
                        silhouette_px: Some(9),
                        ..Default::default()
                    },
                    ..PerceptionArgs::default()
                },
                ..args(out.clone())
            },
            EvalArgs {
                days: Some(7.0),
                visit_every_days: 0.0,
                ..args(out.clone())
            },
            EvalArgs {
                days: Some(-3.0),
                ..args(out.clone())
            },
            EvalArgs {
                perception: PerceptionArgs {
                    fruit_model: Some(out.join("no-such-model.onnx")),
                    ..PerceptionArgs::default()
                },
                ..args(out.clone())
            },
        ];
        for a in bad {
            let msg = format!("{:#}", run(a).unwrap_err());
            assert!(msg.starts_with("--"), "{msg}");
        }
        // An output path below a regular file cannot be created.
        let file = std::env::temp_dir().join(format!("gh-eval-file-{}", std::process::id()));
        std::fs::write(&file, b"x").unwrap();
        let msg = format!("{:#}", run(args(file.join("out"))).unwrap_err());
        assert!(msg.contains("cannot create"), "{msg}");
        let _ = std::fs::remove_file(&file);
    }

    fn summary_fruits_total(out: &Path) -> usize {
        let summary: serde_json::Value =
            serde_json::from_str(&std::fs::read_to_string(out.join("summary.json")).unwrap())
                .unwrap();
        summary["fruits_total"].as_u64().unwrap() as usize
    }

    #[test]
    fn a_small_run_writes_every_output_and_replays() {
        let base = std::env::temp_dir().join(format!("gh-eval-run-{}", std::process::id()));
        let (a, b) = (base.join("a"), base.join("b"));
        run(args(a.clone())).unwrap();
        run(args(b.clone())).unwrap();
        for name in [
            "table.md",
            "summary.json",
            "covered_volume.png",
            "volume_accuracy.png",
            "f1.png",
            "count_ratio.png",
            "trials/ours-uu-0.csv",
            "trials/explo-uu-0.csv",
            "trials/ours-uu-0-fruits.csv",
        ] {
            assert!(a.join(name).is_file(), "{name}");
        }
        // A row per true fruit at least, every row as wide as the header.
        let fruits = std::fs::read_to_string(a.join("trials/ours-uu-0-fruits.csv")).unwrap();
        let total = summary_fruits_total(&a);
        assert!(fruits.lines().count() > total);
        let width = fruits.lines().next().unwrap().split(',').count();
        assert!(fruits.lines().all(|l| l.split(',').count() == width));
        assert_eq!(
            fruits,
            std::fs::read_to_string(b.join("trials/ours-uu-0-fruits.csv")).unwrap()
        );
        for name in ["trials/ours-uu-0.csv", "trials/explo-uu-0.csv"] {
            let x = std::fs::read_to_string(a.join(name)).unwrap();
            assert_eq!(x, std::fs::read_to_string(b.join(name)).unwrap());
            // 0..=4 s and the header.
            assert_eq!(x.lines().count(), 6);
        }
        let summary: serde_json::Value =
            serde_json::from_str(&std::fs::read_to_string(a.join("summary.json")).unwrap())
                .unwrap();
        assert!(summary["ours-uu"]["detected"]["mean"].is_number());
        assert!(summary["fruits_total"].as_u64().unwrap() > 0);
        view_yield_counts_every_view_but_the_last_plan(&a);
        let _ = std::fs::remove_dir_all(&base);
    }

    /// `scripts/view-yield OUT --whole-run` on a run's views CSVs: a row per method and list,
    /// a view per plan that has a next one (what it cost runs to the next plan).
    fn view_yield_counts_every_view_but_the_last_plan(out: &Path) {
        let script = Path::new(env!("CARGO_MANIFEST_DIR")).join("scripts/view-yield");
        let run = std::process::Command::new("python3")
            .arg(&script)
            .arg(out)
            .arg("--whole-run")
            .output()
            .unwrap();
        let table = String::from_utf8(run.stdout).unwrap();
        assert!(run.status.success(), "{table}");
        for method in ["ours-uu", "explo-uu"] {
            let plans = std::fs::read_to_string(out.join(format!("trials/{method}-0-views.csv")))
                .unwrap()
                .lines()
                .count()
                - 1;
            let row = format!("| {method} | all | {} |", plans - 1);
            assert!(table.contains(&row), "{row} not in\n{table}");
        }
        let empty = std::process::Command::new("python3")
            .arg(&script)
            .arg(out.join("no-such-run"))
            .output()
            .unwrap();
        assert!(!empty.status.success());
        assert!(String::from_utf8_lossy(&empty.stderr).contains("views.csv"));
    }

    #[test]
    fn a_season_of_visits_writes_its_report() {
        let out = std::env::temp_dir().join(format!("gh-eval-visits-{}", std::process::id()));
        let season = EvalArgs {
            methods: vec![Method::OursUu],
            days: Some(3.5),
            budget_s: 6.0,
            ..args(out.clone())
        };
        run(season).unwrap();
        let table = std::fs::read_to_string(out.join("visits.md")).unwrap();
        assert!(table.contains("visits on days [0.0, 3.5]"), "{table}");
        assert!(
            table.contains("Identity over consecutive visits"),
            "{table}"
        );
        let seasons: serde_json::Value =
            serde_json::from_str(&std::fs::read_to_string(out.join("visits.json")).unwrap())
                .unwrap();
        assert_eq!(seasons[0]["visits"].as_array().map(Vec::len), Some(2));
        for visit in 0..2 {
            assert!(out
                .join(format!("trials/ours-uu-0-visit{visit}.csv"))
                .is_file());
        }
        let _ = std::fs::remove_dir_all(&out);
    }
}

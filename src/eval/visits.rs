//! `glasshouse eval --days N`: every trial's scene visited every `--visit-every-days` days from
//! day 0 to day N (the simulator's season: fruit grow, set and are harvested, leaves move), one
//! trial per visit, and each fruit followed from visit to visit
//! ([`glasshouse_eval::visits`]). Writes `visits.md` (per method: the paper's figures per visit,
//! identity precision / recall / F1 against the simulator's ids, growth error, time to 95 % of
//! the fruits on a revisit against the first visit), `visits.json` (every trial's figures) and
//! per visit the trial's CSVs (`trials/<method>-<trial>-visit<k>.csv`, `…-fruits.csv`,
//! `…-clusters.csv`, as `eval` writes them for a single visit).

use anyhow::bail;
use glasshouse_eval::visits::{season_figures, IdentityCounts, SeasonFigures, GROWTH_TOLERANCE};
use glasshouse_eval::{mean_std, TrialConfig};
use glasshouse_nbv::season::SeasonRules;

use glasshouse_roimap::PriorRules;

use super::{prepare_out, report, run_trials, write, EvalArgs, Plan, Season};

/// The visit days: 0, every, 2·every, ... up to `days`.
pub(super) fn visit_days(days: f64, every: f64) -> anyhow::Result<Vec<f64>> {
    if !(every.is_finite() && every > 0.0) {
        bail!("--visit-every-days must be above 0");
    }
    if !(days.is_finite() && (0.0..=glasshouse_sim::MAX_DAY).contains(&days)) {
        bail!("--days must be within [0, {}]", glasshouse_sim::MAX_DAY);
    }
    let n = (days / every + 1e-9).floor() as usize + 1;
    Ok((0..n).map(|k| k as f64 * every).collect())
}

pub(super) fn run(args: &EvalArgs, plan: &Plan, days: &[f64]) -> anyhow::Result<()> {
    let start = if args.revisit_from_empty {
        "every revisit from an empty map"
    } else {
        "every revisit from the previous visit's map as a prior"
    };
    eprintln!("{} visits per trial on days {days:?}, {start}", days.len());
    let trials_dir = prepare_out(&args.out)?;
    let configs = configs(args, plan, days)?;
    let prior = PriorRules {
        fruit_below_threshold_logodds: args.prior_fruit_below,
        free_share: args.prior_free_share,
    };
    prior
        .validate()
        .map_err(|e| anyhow::anyhow!("--prior-fruit-below / --prior-free-share: {e}"))?;
    let season = Season {
        visits: days.len(),
        prior: (!args.revisit_from_empty).then_some(prior),
    };
    let results = run_trials(&configs, plan, args.budget_s, season)?;
    let mut per_trial: Vec<Vec<glasshouse_eval::TrialResult>> = Vec::new();
    for (i, (config, result)) in configs.iter().zip(results).enumerate() {
        let Some((result, _)) = result else {
            bail!(
                "trial {} seed {} did not finish",
                config.method,
                config.seed
            );
        };
        let (trial, visit) = (i / days.len(), i % days.len());
        let stem = format!(
            "{}-{}-visit{visit}",
            config.method,
            trial % args.trials as usize
        );
        write(
            &trials_dir.join(format!("{stem}.csv")),
            report::trial_csv(&result),
        )?;
        let fruits = report::fruits_csv(&result);
        write(&trials_dir.join(format!("{stem}-fruits.csv")), fruits)?;
        let clusters = report::clusters_csv(&result);
        write(&trials_dir.join(format!("{stem}-clusters.csv")), clusters)?;
        let views = report::best_views_csv(&result);
        write(&trials_dir.join(format!("{stem}-views.csv")), views)?;
        if visit == 0 {
            per_trial.push(Vec::new());
        }
        if let Some(last) = per_trial.last_mut() {
            last.push(result);
        }
    }
    let seasons: Vec<SeasonFigures> = per_trial
        .iter()
        .map(|visits| season_figures(visits, days, SeasonRules::default()))
        .collect();
    let mut table = String::new();
    for (m, method) in plan.methods.iter().enumerate() {
        let trials = args.trials as usize;
        let of_method = &seasons[m * trials..(m + 1) * trials];
        table.push_str(&method_table(&method.to_string(), of_method, days));
    }
    write(&args.out.join("visits.md"), &table)?;
    write(
        &args.out.join("visits.json"),
        serde_json::to_string_pretty(&seasons)?,
    )?;
    print!("{table}");
    Ok(())
}

/// Trial t of each method on each visit day, in order (method, trial, visit).
fn configs(args: &EvalArgs, plan: &Plan, days: &[f64]) -> anyhow::Result<Vec<TrialConfig>> {
    let base = super::trial_configs(args, plan, args.width * 3 / 4)?;
    let configs: Vec<TrialConfig> = base
        .iter()
        .flat_map(|config| {
            days.iter().map(move |&day| {
                let mut c = *config;
                c.world.scene.day = Some(day);
                c
            })
        })
        .collect();
    Ok(configs)
}

fn fmt(values: &[f64], digits: usize) -> String {
    match mean_std(values) {
        Some(m) => format!("{:.digits$} ± {:.digits$}", m.mean, m.std),
        None => "–".into(),
    }
}

/// One method's visits: a row per visit, then identity, growth and revisit time.
fn method_table(method: &str, seasons: &[SeasonFigures], days: &[f64]) -> String {
    let mut out = format!(
        "## {method}: {} trials, visits on days {days:?}\n\n| day | count ratio | F1 | F1, 5 cm | centre (cm) | volume acc. | time to 95 % (s) | reached | detected at the end | time to the first visit's level (s) | reached |\n|---|---|---|---|---|---|---|---|---|---|---|\n",
        seasons.len()
    );
    for (k, day) in days.iter().enumerate() {
        out.push_str(&visit_row(seasons, k, *day));
    }
    out.push('\n');
    out.push_str(&identity_line(seasons));
    out.push_str(&growth_line(seasons));
    out.push_str(&revisit_lines(seasons));
    out.push('\n');
    out
}

/// The table row of visit `k` (on `day`) over every season.
fn visit_row(seasons: &[SeasonFigures], k: usize, day: f64) -> String {
    let of = |f: fn(&glasshouse_eval::visits::VisitFigures) -> f64| -> Vec<f64> {
        seasons.iter().map(|s| f(&s.visits[k])).collect()
    };
    let times = |f: fn(&glasshouse_eval::visits::VisitFigures) -> Option<u32>| -> Vec<f64> {
        seasons
            .iter()
            .filter_map(|s| f(&s.visits[k]).map(f64::from))
            .collect()
    };
    let (t95, t_level) = (
        times(|v| v.time_to_95_s),
        times(|v| v.time_to_first_level_s),
    );
    format!(
        "| {day} | {} | {} | {} | {} | {} | {} | {} of {} | {} | {} | {} of {} |\n",
        fmt(&of(|v| v.count_ratio), 2),
        fmt(&of(|v| v.f1), 2),
        fmt(&of(|v| v.f1_near), 2),
        fmt(&of(|v| v.centre_cm), 2),
        fmt(&of(|v| v.volume_accuracy), 2),
        fmt(&t95, 0),
        t95.len(),
        seasons.len(),
        fmt(&of(|v| v.detected_share), 2),
        fmt(&t_level, 0),
        t_level.len(),
        seasons.len()
    )
}

/// Identity over consecutive visits, summed over the seasons.
fn identity_line(seasons: &[SeasonFigures]) -> String {
    let mut identity = IdentityCounts::default();
    for s in seasons {
        identity.add(&s.identity);
    }
    let per_trial_f1: Vec<f64> = seasons.iter().map(|s| s.identity.f1()).collect();
    format!(
        "Identity over consecutive visits: precision {:.3}, recall {:.3}, F1 {:.3} ({} correct of {} links made, {} possible; per trial F1 {}).\n",
        identity.precision(),
        identity.recall(),
        identity.f1(),
        identity.correct,
        identity.made,
        identity.possible,
        fmt(&per_trial_f1, 3),
    )
}

/// The growth errors, measured on one shape and differenced, over every season's links.
fn growth_line(seasons: &[SeasonFigures]) -> String {
    let all = |f: fn(&SeasonFigures) -> &Vec<f64>| -> Vec<f64> {
        seasons.iter().flat_map(|s| f(s).iter().copied()).collect()
    };
    let errors = all(|s| &s.growth_errors);
    let differenced = all(|s| &s.differenced_growth_errors);
    let within = errors.iter().filter(|&&e| e <= GROWTH_TOLERANCE).count();
    format!(
        "Growth: {} correct links of growing fruit, |ΔV_est − ΔV_true| / ΔV_true median {:.2}, {} within {:.0} % (measured on one shape; the difference of the two fitted volumes: median {:.2}).\n",
        errors.len(),
        median_of(&errors),
        within,
        GROWTH_TOLERANCE * 100.0,
        median_of(&differenced),
    )
}

/// The revisits' times against their first visits'.
fn revisit_lines(seasons: &[SeasonFigures]) -> String {
    let ratios = revisit_ratios(seasons, |v| v.time_to_95_s);
    let level_ratios = revisit_ratios(seasons, |v| v.time_to_first_level_s);
    format!(
        "Time to 95 % on a revisit against the first visit: {} ({} revisits that reached 95 % after a first visit that did).\n\
         Time to 95 % of what the first visit found, a revisit against the first visit: {} ({} revisits; median {:.2}).\n",
        fmt(&ratios, 2),
        ratios.len(),
        fmt(&level_ratios, 2),
        level_ratios.len(),
        median_of(&level_ratios)
    )
}

/// Every revisit's time against its season's first visit's, where both exist.
fn revisit_ratios(
    seasons: &[SeasonFigures],
    time_s: fn(&glasshouse_eval::visits::VisitFigures) -> Option<u32>,
) -> Vec<f64> {
    seasons
        .iter()
        .flat_map(|s| {
            let first = time_s(&s.visits[0]);
            s.visits[1..]
                .iter()
                .filter_map(move |v| match (first, time_s(v)) {
                    (Some(a), Some(b)) if a > 0 => Some(f64::from(b) / f64::from(a)),
                    _ => None,
                })
        })
        .collect()
}

fn median_of(values: &[f64]) -> f64 {
    let mut sorted = values.to_vec();
    sorted.sort_by(f64::total_cmp);
    sorted.get(sorted.len() / 2).copied().unwrap_or(f64::NAN)
}

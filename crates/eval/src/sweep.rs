//! The orchestration of an evaluation, apart from any command line: every model at every
//! sampler point, raw per-trial rows stored and reused ([`Store`]), summaries, a plot against the
//! swept value, and a section of `report.md` ([`finish`]). A protocol ([`crate::protocols`])
//! produces the rows; [`sweep`] decides which points still need them.

use crate::mean_std;
use crate::protocols::{Bench, Point, setting_name};
use flowmimic_control::StartActions;
use flowmimic_model::TrajectoryModel;
use flowmimic_motion::Clip;
use flowmimic_plot::{Chart, Series};
use flowmimic_sim::Humanoid;
use sha2::{Digest, Sha256};
use std::collections::BTreeMap;
use std::fmt::Write as _;
use std::path::{Path, PathBuf};
use std::sync::Arc;

/// Errors of a sweep: the protocol's, or writing its files.
pub type Error = Box<dyn std::error::Error + Send + Sync>;
pub type Result<T> = std::result::Result<T, Error>;

/// A loaded model, its label and the settings it is evaluated with.
pub struct EvalModel {
    pub label: String,
    pub dir: PathBuf,
    pub model: TrajectoryModel,
    /// SHA-256 of the model's weights and statistics: stored results are keyed by it, so a
    /// retrained model in the same folder is evaluated anew.
    pub content: String,
    /// SHA-256 of its inverse-dynamics file, if any: part of the key of points that execute
    /// its actions.
    pub inverse_content: Option<String>,
    /// Its point for the protocol's task (a command line's flags over its `recommended.toml`):
    /// a sweep varies the scale or the NFE and keeps the rest.
    pub sampler: Point,
    /// The tracking policy that executes its plans, if any ([`flowmimic_control::Executor`]),
    /// with the SHA-256 of its policy file and the share of its residual added, part of every
    /// point's key.
    pub executor: Option<(PathBuf, String, f32)>,
}

impl EvalModel {
    /// A model loaded from `dir` under `label`, with its content hash, evaluated at `sampler`.
    pub fn new(label: &str, dir: &Path, model: TrajectoryModel, sampler: Point) -> Result<Self> {
        let mut h = Sha256::new();
        for file in [flowmimic_model::train::MODEL_FILE, flowmimic_model::train::STATS_FILE] {
            h.update(flowmimic_io::read(&dir.join(file))?);
        }
        let content = format!("{:x}", h.finalize());
        let inverse = dir.join(flowmimic_model::inverse::INVERSE_FILE);
        let inverse_content = match model.inverse {
            Some(_) => Some(format!("{:x}", Sha256::digest(flowmimic_io::read(&inverse)?))),
            None => None,
        };
        Ok(Self { label: label.to_string(), dir: dir.into(), model, content, inverse_content, sampler, executor: None })
    }

    /// This model with its plans executed by the tracking policy of run directory `run`, `residual`
    /// of its residual added to each plan's action.
    pub fn with_executor(mut self, run: &Path, residual: f32) -> Result<Self> {
        flowmimic_control::Executor::load(run)?;
        let file = flowmimic_track::train::policy_file(run);
        let content = format!("{:x}", Sha256::digest(flowmimic_io::read(&file)?));
        self.executor = Some((run.into(), content, residual));
        Ok(self)
    }

    /// The protocols' bench for this model; each run's rollout is written in `rollouts`, if given.
    pub fn bench<'a>(&'a self, humanoid: &'a Arc<Humanoid>, clip: &'a Clip, rollouts: Option<&'a Path>) -> Bench<'a> {
        let executor = self.executor.as_ref().map(|(run, _, share)| (run.as_path(), *share));
        Bench { model: &self.model, humanoid, clip, name: &self.label, rollouts, executor }
    }
}

/// Raw per-trial rows of one experiment, keyed by point, persisted as CSV.
pub struct Store {
    path: PathBuf,
    columns: Vec<&'static str>,
    rows: BTreeMap<String, Vec<Vec<f64>>>,
}

impl Store {
    const KEY: &'static str = "model,objective,horizon,nfe,scale,gradient,execute,seed,trial";

    /// The trials stored in `path`. A file written with other columns (by an older version of
    /// the experiment) is moved aside to `NAME.old.csv` (`NAME.old2.csv`, ...), not overwritten.
    pub fn open(path: PathBuf, columns: &[&'static str]) -> Result<Self> {
        let mut rows: BTreeMap<String, Vec<Vec<f64>>> = BTreeMap::new();
        let text = if path.exists() { flowmimic_io::read_to_string(&path)? } else { String::new() };
        let mut lines = text.lines();
        let header = format!("{},{}", Self::KEY, columns.join(","));
        match lines.next() {
            Some(first) if first == header => {
                for line in lines {
                    let f: Vec<&str> = line.split(',').collect();
                    let values: Option<Vec<f64>> =
                        f.get(9..).map(|v| v.iter().filter_map(|x| x.parse().ok()).collect());
                    if let Some(v) = values.filter(|v| v.len() == columns.len()) {
                        rows.entry(f[..8].join(",")).or_default().push(v);
                    }
                }
            }
            Some(_) => {
                let stem = path.file_stem().and_then(|s| s.to_str()).unwrap_or("trials").to_string();
                let aside = (1..)
                    .map(|n| {
                        path.with_file_name(format!(
                            "{stem}.old{}.csv",
                            if n == 1 { String::new() } else { n.to_string() }
                        ))
                    })
                    .find(|p| !p.exists())
                    .expect("a free name");
                std::fs::rename(&path, &aside)
                    .map_err(|e| format!("moving {} aside to {}: {e}", path.display(), aside.display()))?;
                eprintln!(
                    "{}: stored with other columns (an older version of this experiment); kept as {}",
                    path.display(),
                    aside.display()
                );
            }
            None => {}
        }
        Ok(Self { path, columns: columns.to_vec(), rows })
    }

    /// The point's key: the model (label, and a hash of its content and the protocol's
    /// settings: episode length, start clip, reference dataset), and the sampler settings.
    fn key(m: &EvalModel, settings: &str, point: Point) -> String {
        let h = m.model.layout().spec.horizon;
        let (nfe, w, k, seed) = (point.nfe, point.scale, point.execute, point.seed);
        let g = setting_name(&point.gradient);
        // A non-default guidance interval is a different point; the default keeps older keys.
        let mut steps = point.guidance_steps.map(|(a, b)| format!("\0guided steps {a}..{b}")).unwrap_or_default();
        if let Some(a) = point.adaptive {
            steps += &format!("\0adaptive {}", a.reference);
        }
        if point.inverse_dynamics > 0.0 {
            let inverse = m.inverse_content.as_deref().unwrap_or("none");
            steps += &format!("\0inverse dynamics {} {inverse}", point.inverse_dynamics);
        }
        if point.acceleration > 0.0 {
            steps += &format!("\0acceleration {}", point.acceleration);
        }
        if point.label_scale != 1.0 {
            steps += &format!("\0label scale {}", point.label_scale);
        }
        if point.start_actions != StartActions::default() {
            let inverse = m.inverse_content.as_deref().unwrap_or("none");
            steps += &format!("\0start actions {:?} {inverse}", point.start_actions);
        }
        if point.approach {
            steps += "\0approach";
        }
        if let Some((_, executor, residual)) = &m.executor {
            steps += &format!("\0executor {executor}");
            // Points measured with all of the residual, before it could be shared, keep their keys.
            if *residual != 1.0 {
                steps += &format!(" residual {residual}");
            }
        }
        let inputs = format!("{:x}", Sha256::digest(format!("{}\0{settings}{steps}", m.content)));
        let model = format!("{}@{}", m.label, &inputs[..12]);
        format!("{model},{},{h},{nfe},{w},{g},{k},{seed}", m.model.objective.name())
    }

    /// The point's rows: stored ones when complete, else computed by `run` and stored.
    pub fn point(
        &mut self,
        m: &EvalModel,
        settings: &str,
        point: Point,
        trials: usize,
        run: impl FnOnce() -> Result<Vec<Vec<f64>>>,
    ) -> Result<Vec<Vec<f64>>> {
        let key = Self::key(m, settings, point);
        if let Some(rows) = self.rows.get(&key).filter(|r| r.len() == trials) {
            eprintln!("{key}: reusing {} stored trials from {}", rows.len(), self.path.display());
            return Ok(rows.clone());
        }
        let rows = run()?;
        self.rows.insert(key, rows.clone());
        self.save()?;
        Ok(rows)
    }

    fn save(&self) -> Result<()> {
        let mut text = format!("{},{}\n", Self::KEY, self.columns.join(","));
        for (key, rows) in &self.rows {
            for (t, row) in rows.iter().enumerate() {
                let values: Vec<String> = row.iter().map(|v| format!("{v}")).collect();
                writeln!(text, "{key},{t},{}", values.join(","))?;
            }
        }
        Ok(flowmimic_io::write_atomic(&self.path, text.as_bytes())?)
    }
}

/// Mean and standard deviation of each column.
fn summarise(rows: &[Vec<f64>], columns: &[&str]) -> BTreeMap<String, (f64, f64)> {
    columns
        .iter()
        .enumerate()
        .map(|(j, c)| {
            (c.to_string(), mean_std(&rows.iter().map(|r| r[j]).filter(|v| v.is_finite()).collect::<Vec<_>>()))
        })
        .collect()
}

/// One summarised point for the JSON and the report.
#[derive(serde::Serialize)]
pub struct Summary {
    pub model: String,
    pub dir: String,
    pub objective: String,
    pub horizon: usize,
    /// The tracking run that executed the plans and the share of its residual added; `None`:
    /// the plans' own actions. Part of the point, so runs with and without one stay apart.
    pub executor: Option<ExecutorSummary>,
    /// NFE, scale, seed and every other sampler setting.
    #[serde(flatten)]
    pub point: Point,
    pub trials: usize,
    pub mean: BTreeMap<String, f64>,
    pub std: BTreeMap<String, f64>,
    /// Over the trials with a value, infinite ones included (a time never reached).
    pub median: BTreeMap<String, f64>,
}

/// The executor of a [`Summary`]'s point.
#[derive(serde::Serialize)]
pub struct ExecutorSummary {
    pub run: String,
    pub residual: f32,
}

pub fn summary(m: &EvalModel, point: Point, rows: &[Vec<f64>], columns: &[&str]) -> Summary {
    let s = summarise(rows, columns);
    Summary {
        model: m.label.clone(),
        dir: m.dir.display().to_string(),
        objective: m.model.objective.name().into(),
        horizon: m.model.layout().spec.horizon,
        executor: m
            .executor
            .as_ref()
            .map(|(run, _, residual)| ExecutorSummary { run: run.display().to_string(), residual: *residual }),
        point,
        trials: rows.len(),
        mean: s.iter().map(|(k, v)| (k.clone(), v.0)).collect(),
        std: s.iter().map(|(k, v)| (k.clone(), v.1)).collect(),
        median: columns.iter().enumerate().map(|(j, c)| (c.to_string(), median(rows.iter().map(|r| r[j])))).collect(),
    }
}

/// The median of the values that are not NaN (NaN when there are none).
fn median(values: impl Iterator<Item = f64>) -> f64 {
    let mut v: Vec<f64> = values.filter(|v| !v.is_nan()).collect();
    v.sort_by(f64::total_cmp);
    match v.len() {
        0 => f64::NAN,
        n if n % 2 == 1 => v[n / 2],
        n => 0.5 * (v[n / 2 - 1] + v[n / 2]),
    }
}

/// Machine facts for the report.
fn machine() -> String {
    let cpu = std::fs::read_to_string("/proc/cpuinfo")
        .ok()
        .and_then(|t| {
            t.lines()
                .find(|l| l.starts_with("model name"))
                .map(|l| l.split(':').nth(1).unwrap_or("").trim().to_string())
        })
        .unwrap_or_else(|| "unknown CPU".into());
    let cores = std::thread::available_parallelism().map_or(1, |n| n.get());
    format!("{cpu}, {cores} threads")
}

/// Writes the JSON summary, appends a report section, and says where everything went.
pub fn finish(
    out: &Path,
    models: &[EvalModel],
    (name, title): (&str, &str),
    notes: &str,
    summaries: &[Summary],
    table: String,
) -> Result<()> {
    let json = out.join(format!("{name}.json"));
    let merged = merged_summaries(flowmimic_io::read_to_string(&json).ok().as_deref(), summaries)?;
    flowmimic_io::write_atomic(&json, serde_json::to_string_pretty(&merged)?.as_bytes())?;
    let report = out.join("report.md");
    let mut text = flowmimic_io::read_to_string(&report).unwrap_or_else(|_| "# flowmimic evaluation report\n".into());
    // Quoted where a shell would split or read them, so the command pastes back as it ran.
    let args: Vec<String> = std::env::args()
        .skip(1)
        .map(|a| {
            if a.contains([' ', ';', '|', '&', '*', '(', ')', '\'']) {
                format!("'{}'", a.replace('\'', "'\\''"))
            } else {
                a
            }
        })
        .collect();
    let described: Vec<String> = models.iter().map(|m| described(m, summaries)).collect();
    write!(
        text,
        "\n## {title}\n\n`flowmimic {}` on {} ({})\n\nModels: {}.\n\n{notes}\n\n{table}\nRaw trials: `{name}.csv`; summary: `{name}.json`.\n\n![{name}]({name}.png)\n",
        args.join(" "),
        machine(),
        chrono_now(),
        described.join("; ")
    )?;
    flowmimic_io::write_atomic(&report, text.as_bytes())?;
    println!("{table}");
    eprintln!("wrote {name}.csv, {name}.json, {name}.png/svg and appended to {}", report.display());
    Ok(())
}

/// The JSON summary's points: this run's, and those of earlier runs into the same folder that
/// this run did not measure again (the CSV keeps every point's trials; the summary follows it).
/// A point is its fields other than the statistics; a file that does not read as a list of
/// points is replaced.
fn merged_summaries(earlier: Option<&str>, summaries: &[Summary]) -> Result<Vec<serde_json::Value>> {
    fn identity(v: &serde_json::Value) -> Option<serde_json::Map<String, serde_json::Value>> {
        let mut fields = v.as_object()?.clone();
        for statistic in ["trials", "mean", "std", "median"] {
            fields.remove(statistic);
        }
        Some(fields)
    }
    let new: Vec<serde_json::Value> =
        summaries.iter().map(serde_json::to_value).collect::<std::result::Result<_, _>>()?;
    let measured: Vec<_> = new.iter().filter_map(identity).collect();
    let mut kept: Vec<serde_json::Value> = earlier
        .and_then(|text| serde_json::from_str::<Vec<serde_json::Value>>(text).ok())
        .unwrap_or_default()
        .into_iter()
        .filter(|old| identity(old).is_some_and(|id| !measured.contains(&id)))
        .collect();
    kept.extend(new);
    Ok(kept)
}

/// A model for the report: label, folder, network, and the settings it ran at (the NFEs of its
/// summaries, and how guidance acted).
fn described(m: &EvalModel, summaries: &[Summary]) -> String {
    let c = &m.model.config;
    let mut nfe: Vec<usize> = summaries.iter().filter(|s| s.model == m.label).map(|s| s.point.nfe).collect();
    nfe.dedup();
    let nfe: Vec<String> = nfe.iter().map(ToString::to_string).collect();
    format!(
        "`{}` = `{}` ({}, N {} H {}, d {} x {} layers, {} heads) at NFE {}, {}",
        m.label,
        m.dir.display(),
        m.model.objective.label(),
        c.history,
        c.horizon,
        c.d_model,
        c.layers,
        c.heads,
        nfe.join(", "),
        m.sampler.describe()
    ) + &m
        .executor
        .as_ref()
        .map(|(run, _, share)| format!(", plans executed by `{}` (residual x {share})", run.display()))
        .unwrap_or_default()
}

/// UTC date and time from the system clock (no extra dependency for one timestamp).
fn chrono_now() -> String {
    let secs = std::time::SystemTime::now().duration_since(std::time::UNIX_EPOCH).map_or(0, |d| d.as_secs());
    let days = secs / 86400;
    // Civil date from days since 1970-01-01 (Howard Hinnant's algorithm).
    let z = days as i64 + 719_468;
    let era = z.div_euclid(146_097);
    let doe = z - era * 146_097;
    let yoe = (doe - doe / 1460 + doe / 36524 - doe / 146_096) / 365;
    let doy = doe - (365 * yoe + yoe / 4 - yoe / 100);
    let mp = (5 * doy + 2) / 153;
    let day = doy - (153 * mp + 2) / 5 + 1;
    let month = if mp < 10 { mp + 3 } else { mp - 9 };
    let year = yoe + era * 400 + i64::from(month <= 2);
    format!("{year}-{month:02}-{day:02} {:02}:{:02} UTC", (secs % 86400) / 3600, (secs % 3600) / 60)
}

/// Per-trial rows of one point.
pub type Rows = Result<Vec<Vec<f64>>>;

/// How one experiment is written down: file stem, report heading, raw columns, the column
/// plotted against the swept value, and the Markdown table's header.
pub struct Experiment {
    pub name: &'static str,
    /// What else determines the results (episode length, start clip, reference data).
    pub settings: String,
    pub title: &'static str,
    pub columns: Vec<&'static str>,
    pub plot: &'static str,
    pub x_label: &'static str,
    pub y_label: &'static str,
    pub header: &'static str,
}

/// The points a sweep runs a model at.
pub type Points<'a> = dyn Fn(&EvalModel) -> Vec<Point> + 'a;

/// Runs (or reuses) every model at each of its `points`, one row per trial; plots `plot`
/// against the swept value (NFE when `by_nfe`, else the guidance scale), and the fall rate when recorded;
/// returns the summaries and the Markdown table, whose `row`s each see their model's unguided
/// point (w 0) at the same NFE when the sweep has one.
pub fn sweep(
    exp: &Experiment,
    out: &Path,
    models: &[EvalModel],
    (points, trials, by_nfe): (&Points, usize, bool),
    mut run: impl FnMut(&EvalModel, Point) -> Rows,
    row: impl Fn(&EvalModel, &Summary, Option<&Summary>) -> String,
) -> Result<(Vec<Summary>, String)> {
    let mut stored = Store::open(out.join(format!("{}.csv", exp.name)), &exp.columns)?;
    let x_of = |p: &Point| if by_nfe { p.nfe as f64 } else { f64::from(p.scale) };
    let mut chart = Chart::new(exp.title, exp.x_label, exp.y_label);
    let mut falls = Chart::new(&format!("{}: falls", exp.title), exp.x_label, "fall rate");
    if by_nfe {
        chart = chart.log_x();
        falls = falls.log_x();
    }
    let (mut summaries, mut table) = (Vec::new(), format!("{}\n", exp.header));
    for m in models {
        let (mut line, mut band, mut fell) = (Vec::new(), Vec::new(), Vec::new());
        let points = points(m);
        for &point in &points {
            eprintln!("{}: {} NFE {} w {} ({trials} trials)", exp.name, m.label, point.nfe, point.w());
            let rows = stored.point(m, &exp.settings, point, trials, || run(m, point))?;
            let s = summary(m, point, &rows, &exp.columns);
            let (mean, std) = (s.mean[exp.plot], s.std[exp.plot]);
            line.push((x_of(&point), mean));
            band.push((x_of(&point), mean - std, mean + std));
            if let Some(f) = s.mean.get("fell") {
                fell.push((x_of(&point), *f));
            }
            summaries.push(s);
        }
        let own = &summaries[summaries.len() - points.len()..];
        for s in own {
            // The unguided point: w 0, told nothing where the model has a label to tell.
            let unguided = own
                .iter()
                .filter(|u| u.point.scale == 0.0 && u.point.nfe == s.point.nfe)
                .min_by(|a, b| a.point.label_scale.total_cmp(&b.point.label_scale));
            table.push_str(&row(m, s, unguided));
            table.push('\n');
        }
        let series = Series::line(&m.label, line);
        chart = chart.series(if trials > 1 { series.with_band(band) } else { series });
        falls = falls.series(Series::line(&m.label, fell));
    }
    chart.save(&out.join(exp.name))?;
    if exp.columns.contains(&"fell") {
        falls.save(&out.join(format!("{}_falls", exp.name)))?;
    }
    Ok((summaries, table))
}

#[cfg(test)]
mod tests {
    #[test]
    fn the_median_counts_a_time_never_reached_and_skips_missing_values() {
        let m = |v: &[f64]| super::median(v.iter().copied());
        assert_eq!(m(&[3.0, 1.0, f64::INFINITY]), 3.0);
        assert_eq!(m(&[1.0, f64::INFINITY]), f64::INFINITY);
        assert_eq!(m(&[2.0, f64::NAN, 1.0]), 1.5);
        assert!(m(&[f64::NAN]).is_nan());
    }

    #[test]
    fn the_json_summary_keeps_earlier_points_and_replaces_those_measured_again() {
        use super::{ExecutorSummary, Point, Summary};
        let summary = |scale: f32, rmse: f64| Summary {
            model: "fm".into(),
            dir: "m".into(),
            objective: "fm".into(),
            horizon: 16,
            executor: None,
            point: Point {
                nfe: 5,
                scale,
                execute: 1,
                seed: 0,
                gradient: Default::default(),
                guidance_steps: None,
                adaptive: None,
                inverse_dynamics: 0.0,
                acceleration: 0.0,
                label_scale: 1.0,
                start_actions: Default::default(),
                approach: false,
            },
            trials: 20,
            mean: [("rmse".to_string(), rmse)].into(),
            std: Default::default(),
            median: Default::default(),
        };
        let first =
            serde_json::to_string(&super::merged_summaries(None, &[summary(0.0, 0.8), summary(50.0, 0.5)]).unwrap())
                .unwrap();
        let second = super::merged_summaries(Some(&first), &[summary(50.0, 0.4), summary(100.0, 0.3)]).unwrap();
        let points: Vec<(f64, f64)> =
            second.iter().map(|p| (p["scale"].as_f64().unwrap(), p["mean"]["rmse"].as_f64().unwrap())).collect();
        assert_eq!(points, [(0.0, 0.8), (50.0, 0.4), (100.0, 0.3)]);
        // The same point with an executor is another point: neither replaces the other.
        let executed = Summary {
            executor: Some(ExecutorSummary { run: "executor-fm".into(), residual: 0.5 }),
            ..summary(50.0, 0.35)
        };
        let third = super::merged_summaries(Some(&serde_json::to_string(&second).unwrap()), &[executed]).unwrap();
        assert_eq!(third.len(), 4);
        assert_eq!(third[3]["executor"]["residual"].as_f64(), Some(0.5));
        assert!(third[1]["executor"].is_null());
        assert_eq!(super::merged_summaries(Some("not json"), &[summary(0.0, 0.8)]).unwrap().len(), 1);
    }
}

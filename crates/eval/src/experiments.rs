//! The paper's experiments, each a sweep of a protocol over models and sampler points with its
//! table, notes and the paper's numbers beside ours: what `flowmimic eval ...` runs, callable
//! from a library ([`Study`] holds what every experiment shares).

use crate::outcome::{FOLLOWED_SPEED, FOLLOWED_YAW_RATE, followed};
use crate::protocols::{
    self, Bench, FOREST_CLEAR, FOREST_SECONDS, FOREST_WIDTH, ForestSetup, Point, SEGMENT_SETTLE, TargetHeights,
};
use crate::sweep::{EvalModel, Experiment, Result, Rows, Summary, finish, sweep};
use crate::{frechet_distance, gaussian};
use flowmimic_control::{Hand, JoystickSegment, StepReport, Task};
use flowmimic_data::Dataset;
use flowmimic_model::Gradient;
use flowmimic_motion::Clip;
use flowmimic_sim::{Humanoid, STATE_DIM};
use std::path::Path;
use std::sync::Arc;

/// One protocol's trials, given where to report each control step.
pub type Trials<'a> = dyn Fn(&dyn Fn(&StepReport)) -> Rows + 'a;

/// Runs [`Trials`] lasting `steps` control steps: the caller's progress display wraps the work
/// (a command line draws a bar; a library user may pass `&|_, trials| trials(&|_| {})`).
pub type WithProgress<'a> = dyn Fn(usize, &Trials) -> Rows + 'a;

/// What every experiment of one evaluation shares.
pub struct Study<'a> {
    pub models: &'a [EvalModel],
    pub humanoid: &'a Arc<Humanoid>,
    /// Trials start from frames of this clip.
    pub clip: &'a Clip,
    /// Where CSV, JSON, plots and `report.md` go.
    pub out: &'a Path,
    /// Few trials and short episodes.
    pub quick: bool,
    /// Trials per point, instead of the protocol's own count.
    pub trials: Option<usize>,
    /// Where each point's rollout is written when its trials run (`None`: nowhere; stored
    /// points are not run again).
    pub rollouts: Option<&'a Path>,
    pub progress: &'a WithProgress<'a>,
}

/// The mean time to arrive of the trials that arrived (s), or a dash when none did.
fn time_to_arrive(s: &Summary) -> String {
    cell(s.mean["seconds"], 1)
}

/// A mean with `digits` decimals, or a dash where no trial had one (every trial fell before it).
fn cell(value: f64, digits: usize) -> String {
    if value.is_nan() { "—".to_string() } else { format!("{value:.digits$}") }
}

/// Means with their signs and 2 decimals, each a dash where no trial had one, comma-separated.
fn signed(values: &[f64]) -> String {
    let one = |v: &f64| if v.is_nan() { "—".to_string() } else { format!("{v:+.2}") };
    values.iter().map(one).collect::<Vec<_>>().join(", ")
}

/// The most segments `eval joystick --schedule` reports, and each segment's columns: the mean
/// achieved forward and sideways speed and yaw rate, followed (1) or not (0), and what the plans
/// asked over the same steps (the same three numbers).
pub const MAX_SEGMENTS: usize = 8;
const SEGMENT_COLUMNS: [[&str; 7]; MAX_SEGMENTS] = [
    ["s1_vx", "s1_vy", "s1_yaw_rate", "s1_followed", "s1_planned_vx", "s1_planned_vy", "s1_planned_yaw_rate"],
    ["s2_vx", "s2_vy", "s2_yaw_rate", "s2_followed", "s2_planned_vx", "s2_planned_vy", "s2_planned_yaw_rate"],
    ["s3_vx", "s3_vy", "s3_yaw_rate", "s3_followed", "s3_planned_vx", "s3_planned_vy", "s3_planned_yaw_rate"],
    ["s4_vx", "s4_vy", "s4_yaw_rate", "s4_followed", "s4_planned_vx", "s4_planned_vy", "s4_planned_yaw_rate"],
    ["s5_vx", "s5_vy", "s5_yaw_rate", "s5_followed", "s5_planned_vx", "s5_planned_vy", "s5_planned_yaw_rate"],
    ["s6_vx", "s6_vy", "s6_yaw_rate", "s6_followed", "s6_planned_vx", "s6_planned_vy", "s6_planned_yaw_rate"],
    ["s7_vx", "s7_vy", "s7_yaw_rate", "s7_followed", "s7_planned_vx", "s7_planned_vy", "s7_planned_yaw_rate"],
    ["s8_vx", "s8_vy", "s8_yaw_rate", "s8_followed", "s8_planned_vx", "s8_planned_vy", "s8_planned_yaw_rate"],
];

/// `1.0` for true, so falls and successes average into rates.
fn rate(b: bool) -> f64 {
    f64::from(u8::from(b))
}

impl Study<'_> {
    fn trials(&self, full: usize, quick: usize) -> usize {
        self.trials.unwrap_or(if self.quick { quick } else { full }).max(1)
    }

    /// The protocols' bench for model `m`.
    fn bench<'m>(&'m self, m: &'m EvalModel) -> Bench<'m> {
        m.bench(self.humanoid, self.clip, self.rollouts)
    }

    /// Each model at each of `nfe`, at guidance scale `scale`.
    fn by_nfe(nfe: &[usize], scale: f32) -> impl Fn(&EvalModel) -> Vec<Point> {
        move |m| nfe.iter().map(|&nfe| Point { nfe, scale, ..m.sampler }).collect()
    }

    /// Each model at each of `scales`; none given, at its own scale, beside w 0 when
    /// `unguided` (the protocols that compare with unguided walking), and then, for a labelled
    /// model, beside w 0 told nothing.
    fn by_scale(scales: &[f32], unguided: bool) -> impl Fn(&EvalModel) -> Vec<Point> {
        move |m| {
            let mut w = match (scales.is_empty(), unguided) {
                (false, _) => scales.to_vec(),
                (true, true) => vec![0.0, m.sampler.scale],
                (true, false) => vec![m.sampler.scale],
            };
            w.dedup();
            let mut points: Vec<Point> = w.into_iter().map(|scale| Point { scale, ..m.sampler }).collect();
            // A labelled model told its command steers at w 0: its unguided walk is told nothing.
            if unguided && m.model.layout().labels > 0 && m.sampler.label_scale != 0.0 {
                points.insert(0, Point { scale: 0.0, label_scale: 0.0, ..m.sampler });
            }
            points
        }
    }

    /// What besides the model and the point determines an experiment's results (the start
    /// clip, and `extra`): part of every stored trial's key.
    fn settings(&self, extra: &str) -> String {
        let clip = format!("clip {} {}", self.clip.name, self.clip.len());
        if extra.is_empty() { clip } else { format!("{clip}; {extra}") }
    }

    /// A guided protocol swept over guidance `scales` (each model's own, and w 0 when
    /// `unguided`, if none given), `trials` trials a point lasting `steps` control steps; `rows`
    /// runs a point's trials, `row` and `notes` write it down.
    fn guided_sweep(
        &self,
        exp: &Experiment,
        (scales, unguided, trials, steps): (&[f32], bool, usize, usize),
        rows: impl Fn(&Bench, Point, &dyn Fn(&StepReport)) -> Rows,
        row: impl Fn(&EvalModel, &Summary, Option<&Summary>) -> String,
        notes: &str,
    ) -> Result<()> {
        let (summaries, table) = sweep(
            exp,
            self.out,
            self.models,
            (&Self::by_scale(scales, unguided), trials, false),
            |m, point| (self.progress)(steps, &|report| rows(&self.bench(m), point, report)),
            row,
        )?;
        finish(self.out, self.models, (exp.name, exp.title), notes, &summaries, table)
    }

    /// Unguided walking under kicks against NFE (paper Fig. 2); `seconds` caps each episode
    /// (default 1000 steps, quick 10 s).
    pub fn survival(&self, nfe: &[usize], seconds: Option<f64>) -> Result<()> {
        let settings = self.settings(&format!("seconds {seconds:?}; quick {}", self.quick));
        let trials = self.trials(50, 8);
        let seconds = seconds.unwrap_or(if self.quick { 10.0 } else { 1000.0 / flowmimic_sim::CONTROL_HZ });
        let steps = (seconds * flowmimic_sim::CONTROL_HZ).round() as usize;
        let exp = Experiment {
            name: "survival",
            settings,
            title: "Survival against NFE (paper Fig. 2)",
            columns: vec!["steps"],
            plot: "steps",
            x_label: "NFE",
            y_label: "control steps survived",
            header: "| model | objective | NFE | steps survived (mean ± std) | paper FM / DDPM |\n|---|---|---|---|---|",
        };
        let (summaries, table) = sweep(
            &exp,
            self.out,
            self.models,
            (&Self::by_nfe(nfe, 0.0), trials, true),
            |m, point| {
                (self.progress)(steps, &|report| {
                    let survived = protocols::survival(&self.bench(m), point, trials, seconds, report)?;
                    Ok(survived.iter().map(|&s| vec![s as f64]).collect())
                })
            },
            |m, s, _| {
                let paper = match s.point.nfe {
                    1 => "280 / 30",
                    5 => "820 / 280",
                    20 => "≈470 / ≈470",
                    _ => "",
                };
                format!(
                    "| {} | {} | {} | {:.0} ± {:.0} | {paper} |",
                    m.label, s.objective, s.point.nfe, s.mean["steps"], s.std["steps"]
                )
            },
        )?;
        let notes = format!(
            "Unguided walking, a random planar root-velocity kick of uniform 0-0.5 m/s in a uniform direction every 1 s, \
             failure when the head is below 0.2 m; {trials} trials per point, episode cap {seconds:.1} s ({steps} steps)."
        );
        finish(self.out, self.models, (exp.name, exp.title), &notes, &summaries, table)
    }

    /// Forward, backward, turn left and right, 3 s each, against guidance scale (paper Fig. 3).
    pub fn joystick(&self, scales: &[f32]) -> Result<()> {
        let trials = self.trials(10, 2);
        let exp = Experiment {
            name: "joystick",
            // Points stored before the joystick's heading was held measured another cost.
            settings: self.settings("heading held"),
            title: "Joystick tracking against guidance (paper Fig. 3)",
            columns: vec![
                "velocity_rmse",
                "yaw_rate_rmse",
                "forward_vx",
                "backward_vx",
                "left_yaw_rate",
                "right_yaw_rate",
                "forward_rmse",
                "backward_rmse",
                "left_rmse",
                "right_rmse",
                "fell",
                "forward_followed",
                "backward_followed",
                "left_followed",
                "right_followed",
            ],
            plot: "velocity_rmse",
            x_label: "guidance scale w",
            y_label: "velocity RMSE (m/s)",
            header: "| model | H | w | velocity RMSE (m/s) | times unguided | segment RMSE: forward / backward / left / right (m/s) | yaw-rate RMSE (rad/s) | mean speed: forward / backward (m/s) | mean yaw rate: left / right (rad/s) | followed: forward / backward / left / right | falls |\n|---|---|---|---|---|---|---|---|---|---|---|",
        };
        let notes = format!(
            "Forward 1.0 m/s, backward 0.5 m/s, turn left and right (0.8 m/s at 0.6 rad/s), 3 s each; RMSE between commanded \
             and achieved planar root velocity (character frame) over the steps before any fall; {trials} trials. \
             Per segment, the mean achieved forward velocity (forward, backward; commanded 1.0 and -0.5 m/s) and yaw rate \
             (turns; commanded 0.6 and -0.6 rad/s) from {SEGMENT_SETTLE} s after the segment's start, before any fall, and \
             the velocity RMSE of each segment over all its steps (the change of gait included); \
             followed: the share of trials in which a segment's achieved forward and sideways speed come within \
             {FOLLOWED_SPEED} m/s and its yaw rate within {FOLLOWED_YAW_RATE} rad/s of the command, with no fall; \
             times unguided: the mean RMSE over the same model's at w 0 and this NFE, when the sweep has it. \
             Paper: RMSE ≈ 0.55 at w = 40; 1.05 at H = 2 to 0.70 at H = 16."
        );
        self.guided_sweep(
            &exp,
            (scales, true, trials, 360),
            |bench, point, report| {
                let asked = Task::joystick_eval().joystick;
                let r = protocols::joystick(bench, point, &asked, trials, report)?;
                Ok(r.iter()
                    .map(|t| {
                        let [fwd, back, left, right] =
                            [0, 1, 2, 3].map(|i| t.segments.get(i).copied().unwrap_or([f64::NAN; 3]));
                        let per = [0, 1, 2, 3].map(|i| t.segment_rmse.get(i).copied().unwrap_or(f64::NAN));
                        let followed = [0, 1, 2, 3].map(|i| {
                            let s = &asked[i];
                            rate(!t.fell && t.segments.get(i).is_some_and(|&a| followed([s.vx, s.vy, s.yaw_rate], a)))
                        });
                        vec![t.velocity_rmse, t.yaw_rate_rmse, fwd[0], back[0], left[2], right[2]]
                            .into_iter()
                            .chain(per)
                            .chain([rate(t.fell)])
                            .chain(followed)
                            .collect()
                    })
                    .collect())
            },
            |m, s, unguided| {
                let share = unguided
                    .map_or_else(|| "-".into(), |u| format!("{:.3}", s.mean["velocity_rmse"] / u.mean["velocity_rmse"]));
                let cells = |keys: &[&str], digits| keys.iter().map(|k| cell(s.mean[*k], digits)).collect::<Vec<_>>();
                format!(
                    "| {} | {} | {} | {:.3} ± {:.3} | {share} | {} | {:.3} | {} | {} | {:.0} / {:.0} / {:.0} / {:.0}% | {:.0}% |",
                    m.label,
                    s.horizon,
                    s.point.w(),
                    s.mean["velocity_rmse"],
                    s.std["velocity_rmse"],
                    cells(&["forward_rmse", "backward_rmse", "left_rmse", "right_rmse"], 2).join(" / "),
                    s.mean["yaw_rate_rmse"],
                    cells(&["forward_vx", "backward_vx"], 2).join(" / "),
                    cells(&["left_yaw_rate", "right_yaw_rate"], 2).join(" / "),
                    100.0 * s.mean["forward_followed"],
                    100.0 * s.mean["backward_followed"],
                    100.0 * s.mean["left_followed"],
                    100.0 * s.mean["right_followed"],
                    100.0 * s.mean["fell"]
                )
            },
            &notes,
        )
    }

    /// Any joystick schedule of up to [`MAX_SEGMENTS`] segments, against guidance scale: per
    /// segment, the mean achieved speeds and yaw rate and the share of trials that followed it.
    pub fn joystick_schedule(&self, scales: &[f32], schedule: &[JoystickSegment]) -> Result<()> {
        if schedule.is_empty() || schedule.len() > MAX_SEGMENTS {
            return Err(format!("a schedule of 1 to {MAX_SEGMENTS} segments, not {}", schedule.len()).into());
        }
        let trials = self.trials(8, 2);
        let text: Vec<String> =
            schedule.iter().map(|s| format!("{}:{},{},{}", s.seconds, s.vx, s.vy, s.yaw_rate)).collect();
        let text = text.join(";");
        let mut columns = vec!["velocity_rmse", "yaw_rate_rmse", "fell"];
        columns.extend(SEGMENT_COLUMNS[..schedule.len()].iter().flatten());
        let exp = Experiment {
            name: "joystick-schedule",
            // The schedule is part of what was measured: another one is another experiment.
            settings: self.settings(&format!("schedule {text}")),
            title: "Joystick schedule, segment by segment",
            columns,
            plot: "velocity_rmse",
            x_label: "guidance scale w",
            y_label: "velocity RMSE (m/s)",
            header: "| model | H | w | velocity RMSE (m/s) | segment | asked: forward, sideways (m/s), yaw rate (rad/s) | achieved | planned | followed | falls |\n|---|---|---|---|---|---|---|---|---|---|",
        };
        let notes = format!(
            "Schedule `{text}` (`seconds:vx,vy,yaw_rate` segments); RMSE between commanded and achieved planar root \
             velocity over the steps before any fall; {trials} trials. Per segment, the mean achieved forward and \
             sideways speed and yaw rate from {SEGMENT_SETTLE} s after its start, before any fall, what the plans asked over \
             the same steps (their mean velocity in their own heading and their turn rate over the horizon), and the share \
             of trials that followed it: within {FOLLOWED_SPEED} m/s and {FOLLOWED_YAW_RATE} rad/s of the command, with no fall \
             (7 of 8 is 88%)."
        );
        let steps = (schedule.iter().map(|s| s.seconds).sum::<f64>() * flowmimic_sim::CONTROL_HZ).round() as usize;
        self.guided_sweep(
            &exp,
            (scales, true, trials, steps),
            |bench, point, report| {
                let r = protocols::joystick(bench, point, schedule, trials, report)?;
                Ok(r.iter()
                    .map(|t| {
                        let per = schedule.iter().zip(&t.segments).zip(&t.planned).flat_map(|((s, &a), p)| {
                            [a[0], a[1], a[2], rate(!t.fell && followed([s.vx, s.vy, s.yaw_rate], a)), p[0], p[1], p[2]]
                        });
                        [t.velocity_rmse, t.yaw_rate_rmse, rate(t.fell)].into_iter().chain(per).collect()
                    })
                    .collect())
            },
            |m, s, _| {
                // A row per segment, so that one failing segment stands out.
                let rows: Vec<String> = schedule
                    .iter()
                    .zip(SEGMENT_COLUMNS)
                    .enumerate()
                    .map(|(i, (seg, [vx, vy, yaw, ok, pvx, pvy, pyaw]))| {
                        format!(
                            "| {} | {} | {} | {:.3} | {} | {} | {} | {} | {:.0}% | {:.0}% |",
                            m.label,
                            s.horizon,
                            s.point.w(),
                            s.mean["velocity_rmse"],
                            i + 1,
                            signed(&[seg.vx, seg.vy, seg.yaw_rate]),
                            signed(&[s.mean[vx], s.mean[vy], s.mean[yaw]]),
                            signed(&[s.mean[pvx], s.mean[pvy], s.mean[pyaw]]),
                            100.0 * s.mean[ok],
                            100.0 * s.mean["fell"]
                        )
                    })
                    .collect();
                rows.join("\n")
            },
            &notes,
        )
    }

    /// Random right-hand targets while walking, against guidance scale (paper Fig. 4).
    pub fn reach(&self, scales: &[f32], heights: TargetHeights) -> Result<()> {
        let trials = self.trials(20, 4);
        let label = heights.label();
        let exp = Experiment {
            name: "reach",
            settings: self.settings(&format!("heights {label}")),
            title: "Hand reaching against guidance (paper Fig. 4)",
            columns: vec!["mean", "rms", "min", "reached", "fell"],
            plot: "mean",
            x_label: "guidance scale w",
            y_label: "hand-target distance (m)",
            header: "| model | H | w | mean distance (m) | RMS (m) | closest (m) | within 0.15 m | falls |\n|---|---|---|---|---|---|---|---|",
        };
        let notes = format!(
            "Right-hand targets 1.5-3 m ahead of each trial's start, within 0.5 m to either side, {label} high; 4 s of \
             guided walking on (up to the target, a pursuit command, where a model's settings say approach); distance averaged over the trial (mean, RMS), the closest approach and the share of trials \
             whose hand came within 0.15 m; {trials} trials. Paper: RMSE ≈ 1.1 at w = 100."
        );
        self.guided_sweep(
            &exp,
            (scales, true, trials, 120),
            |bench, point, report| {
                let r = protocols::reach(bench, point, heights, trials, report)?;
                Ok(r.iter().map(|t| vec![t.mean, t.rms, t.min, rate(t.reached()), rate(t.fell)]).collect())
            },
            |m, s, _| {
                format!(
                    "| {} | {} | {} | {:.3} | {:.3} | {:.3} | {:.0}% | {:.0}% |",
                    m.label,
                    s.horizon,
                    s.point.w(),
                    s.mean["mean"],
                    s.mean["rms"],
                    s.mean["min"],
                    100.0 * s.mean["reached"],
                    100.0 * s.mean["fell"]
                )
            },
            &notes,
        )
    }

    /// Reaching while standing: the share of trials whose hand comes within 0.10 m, and the
    /// median time to get there, against guidance scale.
    pub fn reach_standing(&self, scales: &[f32], heights: (f64, f64)) -> Result<()> {
        let trials = self.trials(20, 4);
        let (low, high) = heights;
        let exp = Experiment {
            name: "reach-standing",
            settings: self.settings(&format!("heights {low}-{high} m")),
            title: "Reaching while standing",
            // Per trial: its target's height, the hand's and the plans' closest approach; whether
            // its target is low, and whether it reached, was planned to and fell as a low one, so
            // that the row can say how the low targets and the others fare apart.
            columns: vec![
                "height",
                "closest",
                "planned_closest",
                "reached",
                "seconds",
                "fell",
                "low",
                "low_reached",
                "low_fell",
                "planned",
                "low_planned",
            ],
            plot: "reached",
            x_label: "guidance scale w",
            y_label: "share within 0.10 m",
            header: "| model | H | w | closest (m) | within 0.10 m | planned within 0.10 m | median time to reach (s) | falls | targets below 0.9 m: within 0.10 m / planned / falls | the others |\n|---|---|---|---|---|---|---|---|---|---|",
        };
        let (near, far) = protocols::STANDING_DISTANCES;
        let notes = format!(
            "Standing (a zero joystick command), the right hand asked for a target {low}-{high} m high, {near}-{far} m out \
             from where the right shoulder starts (horizontally, from straight ahead to straight out to the side); 4 s; \
             reached when the hand comes within {} m; the median time to reach counts a trial that never reaches as \
             never (a dash when half or more never do); planned: a plan put the hand there at its horizon's end (H steps ahead, \
             0.53 s at H 16), set beside the hand to tell a plan that misses from an execution that misses a plan; targets below {} m, which ask the walker to bend, and the \
             others each get their own share within reach and of falls; {trials} trials.",
            protocols::STANDING_REACHED,
            protocols::STANDING_LOW
        );
        self.guided_sweep(
            &exp,
            (scales, true, trials, 120),
            |bench, point, report| {
                let r = protocols::reach_standing(bench, point, heights, trials, report)?;
                Ok(r.iter()
                    .map(|t| {
                        let (reached, low) =
                            (rate(t.seconds_to_reach.is_finite()), rate(t.height < protocols::STANDING_LOW));
                        let fell = rate(t.reach.fell);
                        let planned = rate(t.reach.planned_min <= protocols::STANDING_REACHED);
                        vec![
                            t.height,
                            t.reach.min,
                            t.reach.planned_min,
                            reached,
                            t.seconds_to_reach,
                            fell,
                            low,
                            low * reached,
                            low * fell,
                            planned,
                            low * planned,
                        ]
                    })
                    .collect())
            },
            |m, s, _| {
                let median = s.median["seconds"];
                let median = if median.is_finite() { format!("{median:.2}") } else { "—".into() };
                // Shares within each group of targets, from the means of the per-trial columns.
                let (low, high) = (s.mean["low"], 1.0 - s.mean["low"]);
                let share =
                    |part: f64, of: f64| if of > 0.0 { format!("{:.0}%", 100.0 * part / of) } else { "—".into() };
                let (low_reached, low_fell, low_planned) = (s.mean["low_reached"], s.mean["low_fell"], s.mean["low_planned"]);
                format!(
                    "| {} | {} | {} | {:.3} | {:.0}% | {:.0}% | {median} | {:.0}% | {} / {} / {} of {:.0}% | {} / {} / {} |",
                    m.label,
                    s.horizon,
                    s.point.w(),
                    s.mean["closest"],
                    100.0 * s.mean["reached"],
                    100.0 * s.mean["planned"],
                    100.0 * s.mean["fell"],
                    share(low_reached, low),
                    share(low_planned, low),
                    share(low_fell, low),
                    100.0 * low,
                    share(s.mean["reached"] - low_reached, high),
                    share(s.mean["planned"] - low_planned, high),
                    share(s.mean["fell"] - low_fell, high),
                )
            },
            &notes,
        )
    }

    /// Waypoint navigation: arrival rate against guidance scale.
    pub fn waypoint(&self, scales: &[f32]) -> Result<()> {
        let trials = self.trials(20, 4);
        let exp = Experiment {
            name: "waypoint",
            settings: self.settings(""),
            title: "Waypoint navigation",
            columns: vec!["arrived", "closest", "seconds", "last", "fell"],
            plot: "arrived",
            x_label: "guidance scale w",
            y_label: "arrival rate",
            header: "| model | w | arrived | closest (m) | time to arrive (s) | distance at the end (m) | falls |\n|---|---|---|---|---|---|---|",
        };
        let notes = format!(
            "Goal 3-4 m from each trial's start at a bearing within 90 degrees of its heading; 10 s; arrived when the pelvis \
             comes within 0.5 m of it; time to arrive averaged over the trials that arrive; the distance at the end (10 s or a fall) \
             says whether it stays; {trials} trials."
        );
        self.guided_sweep(
            &exp,
            (scales, true, trials, 300),
            |bench, point, report| {
                let r = protocols::waypoint(bench, point, trials, report)?;
                Ok(r.iter()
                    .map(|t| {
                        vec![rate(t.arrival.is_some()), t.closest, t.arrival.unwrap_or(f64::NAN), t.last, rate(t.fell)]
                    })
                    .collect())
            },
            |m, s, _| {
                format!(
                    "| {} | {} | {:.0}% | {:.2} | {} | {:.2} | {:.0}% |",
                    m.label,
                    s.point.w(),
                    100.0 * s.mean["arrived"],
                    s.mean["closest"],
                    time_to_arrive(s),
                    s.mean["last"],
                    100.0 * s.mean["fell"]
                )
            },
            &notes,
        )
    }

    /// Walking through a forest of obstacles to a goal: success rate against guidance scale,
    /// and each trial's collisions, fall and time to the goal.
    pub fn forest(&self, scales: &[f32], setup: ForestSetup) -> Result<()> {
        let trials = self.trials(20, 4);
        let world = if setup.moving { "moving" } else { "standing" };
        let exp = Experiment {
            name: if setup.blind { "forest-blind" } else { "forest" },
            settings: self
                .settings(&format!("{world}; blind {}; clear {FOREST_CLEAR}; width {FOREST_WIDTH}", setup.blind)),
            title: "Through a forest to a goal",
            columns: vec!["success", "arrived", "contacts", "fell", "seconds", "obstacles"],
            plot: "success",
            x_label: "guidance scale w",
            y_label: "success rate",
            header: "| model | w | success | arrived | touched an obstacle | falls | time to goal (s) |\n|---|---|---|---|---|---|---|",
        };
        let world = match setup.moving {
            true => {
                "2-3 cylinders of radius 0.3-0.4 m crossing the way at 0.5-1.0 m/s, each where a walker at 0.8 m/s meets it"
            }
            false => &format!(
                "10-20 standing cylinders of radius 0.2-0.5 m within {FOREST_WIDTH} m of the way and {FOREST_CLEAR} m of the \
                 start and the goal, at least 1 m apart"
            ),
        };
        let blind = match setup.blind {
            true => " Baseline: guidance ignores the obstacles (the waypoint's pursuit alone); they are still solid.",
            false => "",
        };
        let notes = format!(
            "Goal 8-10 m straight ahead; {world}; {FOREST_SECONDS} s; success when the pelvis comes within 0.5 m of the goal \
             with no contact (MuJoCo's) between the humanoid and an obstacle and no fall; time to the goal averaged over the \
             trials that arrive; {trials} trials.{blind}"
        );
        let steps = (FOREST_SECONDS * flowmimic_sim::CONTROL_HZ) as usize;
        self.guided_sweep(
            &exp,
            (scales, false, trials, steps),
            |bench, point, report| {
                let r = protocols::forest(bench, point, setup, trials, report)?;
                eprintln!("trial  obstacles  success  arrived (s)  steps touching  fell");
                for (i, t) in r.iter().enumerate() {
                    let arrived = t.arrival.map_or("-".to_string(), |a| format!("{a:.1}"));
                    eprintln!(
                        "{i:>5}  {:>9}  {:>7}  {arrived:>11}  {:>14}  {}",
                        t.obstacles,
                        if t.success() { "yes" } else { "no" },
                        t.contact_steps,
                        if t.fell { "yes" } else { "no" }
                    );
                }
                Ok(r.iter()
                    .map(|t| {
                        vec![
                            rate(t.success()),
                            rate(t.arrival.is_some()),
                            rate(t.contact_steps > 0),
                            rate(t.fell),
                            t.arrival.unwrap_or(f64::NAN),
                            t.obstacles as f64,
                        ]
                    })
                    .collect())
            },
            |m, s, _| {
                format!(
                    "| {} | {} | {:.0}% | {:.0}% | {:.0}% | {:.0}% | {} |",
                    m.label,
                    s.point.w(),
                    100.0 * s.mean["success"],
                    100.0 * s.mean["arrived"],
                    100.0 * s.mean["contacts"],
                    100.0 * s.mean["fell"],
                    time_to_arrive(s)
                )
            },
            &notes,
        )
    }

    /// A waypoint and a hand target at once: success rate against guidance scale.
    pub fn compose(&self, scales: &[f32], heights: TargetHeights) -> Result<()> {
        let height = heights.label();
        let trials = self.trials(20, 4);
        let exp = Experiment {
            name: "compose",
            settings: self.settings(&format!("target height {height}")),
            title: "Composition: waypoint and reach",
            columns: vec!["success", "pelvis_min", "hand_min", "fell"],
            plot: "success",
            x_label: "guidance scale w",
            y_label: "success rate",
            header: "| model | w | success | closest pelvis (m) | closest hand (m) | falls |\n|---|---|---|---|---|---|",
        };
        let notes = format!(
            "Waypoint 3-4 m ahead and up to 1.5 m aside; right-hand target 0.4 m right of it at {height}; 10 s (where a model's settings \
             say approach, walking up to the hand target within {} m of the waypoint); success when the pelvis is within \
             0.5 m of the waypoint and the hand within 0.15 m of the target at the same step; {trials} trials.",
            Task::WAYPOINT_RADIUS
        );
        self.guided_sweep(
            &exp,
            (scales, false, trials, 300),
            |bench, point, report| {
                let r = protocols::compose(bench, point, heights, trials, report)?;
                Ok(r.iter().map(|t| vec![rate(t.success), t.pelvis_min, t.hand_min, rate(t.fell)]).collect())
            },
            |m, s, _| {
                format!(
                    "| {} | {} | {:.0}% | {:.2} | {:.2} | {:.0}% |",
                    m.label,
                    s.point.w(),
                    100.0 * s.mean["success"],
                    s.mean["pelvis_min"],
                    s.mean["hand_min"],
                    100.0 * s.mean["fell"]
                )
            },
            &notes,
        )
    }

    /// Fréchet distance of unguided generated walking to `dataset`'s states, against NFE.
    pub fn quality(&self, dataset: &Path, nfe: &[usize]) -> Result<()> {
        let trials = self.trials(16, 4);
        let seconds = if self.quick { 4.0 } else { 10.0 };
        let reference = dataset_features(dataset)?;
        let (rm, rs) = gaussian(&reference);
        // The floor: alternate 10 s blocks of the reference against each other.
        let (even, odd): (Vec<_>, Vec<_>) = reference.iter().enumerate().partition(|(i, _)| (i / 300) % 2 == 0);
        let half = |v: Vec<(usize, &Vec<f64>)>| gaussian(&v.into_iter().map(|(_, f)| f.clone()).collect::<Vec<_>>());
        let ((am, a_s), (bm, bs)) = (half(even), half(odd));
        let floor = frechet_distance(&am, &a_s, &bm, &bs);
        let exp = Experiment {
            name: "quality",
            settings: self.settings(&format!("dataset {}; quick {}", Dataset::open(dataset)?.shards_key(), self.quick)),
            title: "Motion quality (Fréchet distance to the data)",
            columns: vec!["frechet"],
            plot: "frechet",
            x_label: "NFE",
            y_label: "Fréchet distance",
            header: "| model | NFE | Fréchet distance |\n|---|---|---|",
        };
        let steps = (seconds * flowmimic_sim::CONTROL_HZ) as usize;
        let (summaries, table) = sweep(
            &exp,
            self.out,
            self.models,
            (&Self::by_nfe(nfe, 0.0), 1, true),
            |m, point| {
                (self.progress)(steps, &|report| {
                    let f = protocols::generated_features(&self.bench(m), point, trials, seconds, report)?;
                    let (gm, gs) = gaussian(&f);
                    Ok(vec![vec![frechet_distance(&gm, &gs, &rm, &rs)]])
                })
            },
            |m, s, _| format!("| {} | {} | {:.4} |", m.label, s.point.nfe, s.mean["frechet"]),
        )?;
        let table = format!("{table}| reference against itself (floor) | – | {floor:.4} |\n");
        let notes = format!(
            "Features per control step: root height, root velocity (character frame), and head, hand and foot positions \
             relative to the root (19 numbers); Gaussian fits of unguided generated walking ({trials} trials x {seconds} s, \
             steps before any fall) against every state of `{}`; the floor compares alternate 10 s blocks of the data.",
            dataset.display()
        );
        finish(self.out, self.models, (exp.name, exp.title), &notes, &summaries, table)
    }

    /// Time per control step (batch 1) against NFE; guided at scale `guided` if given.
    pub fn latency(&self, nfe: &[usize], guided: Option<f32>) -> Result<()> {
        let scale = guided.unwrap_or(0.0);
        let exp = Experiment {
            name: if guided.is_some() { "latency_guided" } else { "latency" },
            settings: self.settings(""),
            title: if guided.is_some() {
                "Latency per guided control step (batch 1)"
            } else {
                "Latency per control step (batch 1)"
            },
            columns: vec!["model_ms", "physics_ms", "total_ms"],
            plot: "total_ms",
            x_label: "NFE",
            y_label: "milliseconds",
            header: "| model | objective | NFE | model ms | physics ms | control Hz |\n|---|---|---|---|---|---|",
        };
        let (summaries, table) = sweep(
            &exp,
            self.out,
            self.models,
            (&Self::by_nfe(nfe, scale), 1, true),
            |m, point| {
                let (model_ms, physics_ms) = protocols::latency(&self.bench(m), point, 3.0)?;
                Ok(vec![vec![model_ms, physics_ms, model_ms + physics_ms]])
            },
            |m, s, _| {
                format!(
                    "| {} | {} | {} | {:.2} | {:.2} | {:.0} |",
                    m.label,
                    s.objective,
                    s.point.nfe,
                    s.mean["model_ms"],
                    s.mean["physics_ms"],
                    1e3 / s.mean["total_ms"]
                )
            },
        )?;
        let walking = match guided {
            Some(w) => format!("walking guided at w = {w} on the joystick schedule"),
            None => "unguided walking".into(),
        };
        let notes = format!(
            "Median over 3 s of {walking} with one environment; model = one sampling call (all NFE steps), \
             physics = one 30 Hz step. Paper: FM about 4x faster than DDPM for the same robustness (NFE 5 vs 20)."
        );
        finish(self.out, self.models, (exp.name, exp.title), &notes, &summaries, table)
    }

    /// How far guidance moves the executed action against the later predicted actions, and the
    /// task's error, through the network and of the cost only (the model's output alone).
    pub fn guidance(&self, scales: &[f32], samples: usize) -> Result<()> {
        let walk = |vx, yaw_rate| JoystickSegment { seconds: 1.0, vx, vy: 0.0, yaw_rate };
        let tasks = [
            ("backward -0.5 m/s", Task { joystick: vec![walk(-0.5, 0.0)], ..Task::walk() }),
            ("turn left 0.6 rad/s", Task { joystick: vec![walk(0.8, 0.6)], ..Task::walk() }),
            (
                "right hand 0.5 m ahead, 1.3 m high",
                Task { reach: Some((Hand::Right, [0.5, -0.3, 1.3])), ..Task::walk() },
            ),
        ];
        println!(
            "{:<10} {:<36} {:<16} {:>6} {:>10} {:>10} {:>7} {:>10} {:>10}",
            "model", "task", "gradient", "w", "|da_t|", "|da_t+k|", "ratio", "error", "unguided"
        );
        let mut rows = Vec::new();
        for m in self.models {
            for (name, task) in &tasks {
                for gradient in [Gradient::ThroughNetwork, Gradient::CostOnly] {
                    for &scale in scales {
                        // The model's output alone: its NFE and guided solver steps count.
                        let point = Point { scale, execute: 1, seed: 0, gradient, ..m.sampler };
                        let e = protocols::guidance_effect(&self.bench(m), task, point, samples)?;
                        println!(
                            "{:<10} {:<36} {:<16} {:>6} {:>10.4} {:>10.4} {:>7.2} {:>10.3} {:>10.3}",
                            m.label,
                            name,
                            protocols::setting_name(&gradient),
                            scale,
                            e.first_action,
                            e.later_actions,
                            e.first_action / e.later_actions.max(1e-12),
                            e.error_guided,
                            e.error_unguided
                        );
                        rows.push(serde_json::json!({"model": m.label, "task": name, "gradient": gradient, "scale": scale, "nfe": point.nfe, "samples": samples, "effect": e}));
                    }
                }
            }
        }
        flowmimic_io::write_atomic(&self.out.join("guidance.json"), serde_json::to_string_pretty(&rows)?.as_bytes())?;
        eprintln!("wrote {}", self.out.join("guidance.json").display());
        Ok(())
    }
}

/// Quality features of every state in a dataset.
fn dataset_features(dir: &Path) -> Result<Vec<Vec<f64>>> {
    let dataset = Dataset::open(dir)?;
    let mut out = Vec::new();
    for (_, shard) in dataset.load_all()? {
        out.extend(shard.state.chunks_exact(STATE_DIM).map(protocols::quality_features));
    }
    if out.len() < 100 {
        return Err(format!("{}: only {} states, too few for a reference", dir.display(), out.len()).into());
    }
    Ok(out)
}

#[cfg(test)]
mod tests {
    use super::{cell, signed};

    #[test]
    fn a_mean_no_trial_had_is_a_dash_not_nan() {
        assert_eq!((cell(0.4567, 2), cell(f64::NAN, 2)), ("0.46".to_string(), "—".to_string()));
        assert_eq!(signed(&[1.0, -0.25, f64::NAN]), "+1.00, -0.25, —");
    }
}

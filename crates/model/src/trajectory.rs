//! The trajectory model: a [`Transformer`] over one token per time step of a window, with the
//! dataset's normalisation, trained with Flow Matching, MeanFlow or DDPM, and its sampling API.
//!
//! A window interleaves states and actions, `[s_{t-N}, a_{t-N}, ..., s_t, a_t, ..., s_{t+H}, a_{t+H}]`.
//! Its prefix up to and including `s_t` is the conditioning `O_t` (clean); the rest is the
//! future `tau_t = [a_t, s_{t+1}, a_{t+1}, ...]` that the model denoises. By default token k is
//! `[s_{t-N+k}, a_{t-N+k}]`, so the network sees `concat(O_t, tau_t)` reshaped to
//! `(N + 1 + H) x (state + action)` ([`Pairing`] offers other cuts); which entries are clean is
//! fixed by position, and each position has its own learned embedding. The loss and the sampler
//! only look at `tau_t`.

use crate::fm::{self, Solver};
use crate::inverse::InverseDynamics;
use crate::{Gradient, Guidance, Network, ddpm, meanflow, path};
use flowmimic_data::{Stats, WindowSpec};
use flowmimic_nn::{Transformer, TransformerConfig};
use rand::rngs::StdRng;
use rand::{Rng, SeedableRng};
use rand_distr::{Distribution, StandardNormal};
use serde::{Deserialize, Serialize};

/// Where conditioning and future lie in a window.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
pub struct TokenLayout {
    pub state_dim: usize,
    pub action_dim: usize,
    pub spec: WindowSpec,
    /// Entries of the label at the end of the conditioning: [`Label::TASK`] or
    /// [`Label::COMMAND`] for a labelled model (`ModelConfig::task_labels` or
    /// `command_labels`), else none.
    #[serde(default)]
    pub labels: usize,
}

/// What a window's motion does, as a model with task labels is told (a one-hot; all zeros:
/// not said).
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum TaskLabel {
    Walk,
    Reach,
}

impl TaskLabel {
    pub const ALL: [TaskLabel; 2] = [TaskLabel::Walk, TaskLabel::Reach];
}

/// What a labelled model is told of a window, in entries at the end of its conditioning.
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum Label {
    /// Whether it walks or reaches (a model with task labels): a one-hot.
    Task(TaskLabel),
    /// The motion ahead (a model with command labels): forward and leftward speed (m/s) and yaw
    /// rate (rad/s), as [`flowmimic_data::future_motion`] reads the steps after a window and a
    /// joystick asks, after a 1 that says it is given.
    Command([f32; 3]),
}

impl Label {
    /// Entries of a task label.
    pub const TASK: usize = TaskLabel::ALL.len();
    /// Entries of a command label.
    pub const COMMAND: usize = 4;
}

impl TokenLayout {
    pub fn token_dim(&self) -> usize {
        self.state_dim + self.action_dim
    }

    pub fn tokens(&self) -> usize {
        self.spec.history + 1 + self.spec.horizon
    }

    /// Length of a whole window: the interleaved steps and the task label.
    pub fn window_len(&self) -> usize {
        self.tokens() * self.token_dim() + self.labels
    }

    /// Length of the conditioning `O_t`: N (state, action) pairs, `s_t` and the task label.
    pub fn cond_len(&self) -> usize {
        self.label_at() + self.labels
    }

    /// The current state `s_t` of a conditioning row (before its task label).
    pub fn current_state<'a>(&self, cond: &'a [f32]) -> &'a [f32] {
        &cond[self.label_at() - self.state_dim..self.label_at()]
    }

    /// Where the task label starts: after `s_t`.
    fn label_at(&self) -> usize {
        self.spec.history * self.token_dim() + self.state_dim
    }

    /// The task label's entries in a conditioning row or a window.
    pub fn label_range(&self) -> std::ops::Range<usize> {
        self.label_at()..self.label_at() + self.labels
    }

    /// The label entries for `label`: zeros for none, or for a label of the other kind than
    /// the model's (a model without labels: empty).
    pub fn label(&self, label: Option<Label>) -> Vec<f32> {
        let mut out = vec![0.0; self.labels];
        match label {
            Some(Label::Task(l)) if self.labels == Label::TASK => {
                out[TaskLabel::ALL.iter().position(|&a| a == l).expect("every label is in ALL")] = 1.0;
            }
            Some(Label::Command(c)) if self.labels == Label::COMMAND => {
                out[0] = 1.0;
                out[1..].copy_from_slice(&c);
            }
            _ => {}
        }
        out
    }

    /// The conditioning `O_t` of the history's `states` (N + 1) and `actions` (N) for `label`.
    pub fn conditioning(&self, states: &[f32], actions: &[f32], label: Option<Label>) -> Vec<f32> {
        let mut out = self.interleave(states, actions);
        out.extend(self.label(label));
        out
    }

    /// A whole window of `states` and `actions` (N + 1 + H each) for `label`.
    pub fn window(&self, states: &[f32], actions: &[f32], label: Option<Label>) -> Vec<f32> {
        let mut out = self.interleave(states, actions);
        let at = self.label_at();
        out.splice(at..at, self.label(label));
        out
    }

    /// Length of the future `tau_t`.
    pub fn future_len(&self) -> usize {
        self.window_len() - self.cond_len()
    }

    /// Interleaves `states` (k x state) and `actions` (k or k - 1 x action) as
    /// `[s_0, a_0, s_1, a_1, ...]` (no task label).
    pub fn interleave(&self, states: &[f32], actions: &[f32]) -> Vec<f32> {
        let (sd, ad) = (self.state_dim, self.action_dim);
        let mut out = Vec::with_capacity(states.len() + actions.len());
        for (k, s) in states.chunks_exact(sd).enumerate() {
            out.extend_from_slice(s);
            out.extend_from_slice(actions.get(k * ad..(k + 1) * ad).unwrap_or(&[]));
        }
        out
    }
}

/// Model sizes and the window they cover (a preset's `[model]` table).
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct ModelConfig {
    /// History N (past states and actions the model is conditioned on).
    pub history: usize,
    /// Prediction horizon H.
    pub horizon: usize,
    /// Width of the Transformer's tokens.
    pub d_model: usize,
    /// Attention heads per layer (d_model divides among them).
    pub heads: usize,
    /// Transformer blocks.
    pub layers: usize,
    /// Width of each block's feed-forward layer.
    pub d_ff: usize,
    /// Sinusoidal features of the noise level (even; split between the times of MeanFlow).
    pub time_features: usize,
    /// Which state an action shares its token with.
    pub pairing: Pairing,
    /// Whether the network is told what each window does ([`TaskLabel`], with its noise level):
    /// trained with the label of its clip (`[train] reach_clips`), sampled with the task's.
    pub task_labels: bool,
    /// Whether the network is told the motion of each window's future ([`Label::Command`], with
    /// its noise level): trained with the window's own, sampled with what the task asks of the
    /// pelvis (the joystick's command, or the pursuit of a waypoint), so that a command selects
    /// the data's motion instead of guidance pulling the plan's states toward it.
    #[serde(default)]
    pub command_labels: bool,
    /// For command labels: the steps ahead whose motion labels a window in training (0: the
    /// horizon H). Longer than H, the label tells where the motion goes beyond the plan, which
    /// the history cannot: a command of standing still or walking back to a walker still
    /// walking forward.
    #[serde(default)]
    pub command_steps: usize,
}

/// How a window's states and actions are cut into tokens.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum Pairing {
    /// Token k is `[s_k, a_k]`: the executed action `a_t` sits in the token of the clean
    /// current state, and reaches the future only by attention.
    #[default]
    StateAction,
    /// Token k is `[a_{k-1}, s_k]` (padded with zeros at both ends): an action shares its token
    /// with the state it leads to, so a guided `s_{t+1}` is in the same token as `a_t`, and no
    /// token mixes clean and noisy entries.
    ActionState,
    /// Token k is `[s_k, a_k, s_{k+1}]` (the last padded): an action sees both the state it is
    /// taken in and the state it leads to in its own token. Each state enters two tokens and is
    /// predicted in the first, beside the action that leads to it.
    StateActionState,
}

impl Pairing {
    /// Width of a token.
    fn token_dim(self, layout: &TokenLayout) -> usize {
        match self {
            Pairing::StateActionState => 2 * layout.state_dim + layout.action_dim,
            _ => layout.token_dim(),
        }
    }

    /// Tokens per sample: one per step (and a padding one for `ActionState`).
    fn tokens(self, layout: &TokenLayout) -> usize {
        layout.tokens() + usize::from(self == Pairing::ActionState)
    }

    /// For each entry of a sample's tokens, the window entry it holds (`None`: zero padding).
    /// A label is in no token: it joins the noise level's embedding ([`TrajectoryNet::forward`]).
    fn gather(self, layout: &TokenLayout) -> Vec<Option<usize>> {
        let (at, labels) = (layout.label_at(), layout.labels);
        let steps = self.gather_steps(&TokenLayout { labels: 0, ..*layout });
        steps.into_iter().map(|j| j.map(|j| if j >= at { j + labels } else { j })).collect()
    }

    /// [`Pairing::gather`] of a layout without a label.
    fn gather_steps(self, layout: &TokenLayout) -> Vec<Option<usize>> {
        let (w, sd, td) = (layout.window_len(), layout.state_dim, layout.token_dim());
        match self {
            Pairing::StateAction => (0..w).map(Some).collect(),
            Pairing::ActionState => {
                let pad = |k| std::iter::repeat_n(None, k);
                pad(layout.action_dim).chain((0..w).map(Some)).chain(pad(sd)).collect()
            }
            Pairing::StateActionState => (0..layout.tokens())
                .flat_map(|k| {
                    let next = (k + 1 < layout.tokens()).then_some((k + 1) * td);
                    (k * td..(k + 1) * td).map(Some).chain((0..sd).map(move |j| next.map(|at| at + j)))
                })
                .collect(),
        }
    }
}

impl Default for ModelConfig {
    /// The `cpu` preset: about 0.8 M parameters.
    fn default() -> Self {
        Self {
            history: 4,
            horizon: 8,
            d_model: 128,
            heads: 4,
            layers: 4,
            d_ff: 512,
            time_features: 64,
            pairing: Pairing::default(),
            task_labels: false,
            command_labels: false,
            command_steps: 0,
        }
    }
}

impl ModelConfig {
    /// Refuses sizes no network can have (or no machine can hold), naming the key.
    pub fn validate(&self) -> Result<(), String> {
        let within = |v: usize, lo: usize, hi: usize, key: &str| {
            if (lo..=hi).contains(&v) { Ok(()) } else { Err(format!("model.{key} is {v}; it must be {lo}-{hi}")) }
        };
        within(self.history, 0, 64, "history")?;
        within(self.horizon, 1, 128, "horizon")?;
        within(self.d_model, 1, 4096, "d_model")?;
        within(self.heads, 1, 64, "heads")?;
        within(self.layers, 1, 64, "layers")?;
        within(self.d_ff, 1, 65536, "d_ff")?;
        within(self.time_features, 2, 1024, "time_features")?;
        within(self.command_steps, 0, 900, "command_steps")?;
        if !self.d_model.is_multiple_of(self.heads) {
            return Err(format!("model.d_model ({}) must be a multiple of model.heads ({})", self.d_model, self.heads));
        }
        if self.task_labels && self.command_labels {
            return Err("model.task_labels and model.command_labels: a model has one kind of label".into());
        }
        if !self.time_features.is_multiple_of(2) {
            return Err(format!("model.time_features ({}) must be even", self.time_features));
        }
        Ok(())
    }

    pub fn spec(&self) -> WindowSpec {
        WindowSpec { history: self.history, horizon: self.horizon }
    }

    /// The steps ahead whose motion labels a window of a model with command labels.
    pub fn label_steps(&self) -> usize {
        if self.command_steps == 0 { self.horizon } else { self.command_steps }
    }

    /// Label entries of this model's windows.
    pub fn labels(&self) -> usize {
        match (self.task_labels, self.command_labels) {
            (true, _) => Label::TASK,
            (_, true) => Label::COMMAND,
            _ => 0,
        }
    }

    pub fn transformer(&self, layout: &TokenLayout) -> TransformerConfig {
        TransformerConfig {
            token_dim: self.pairing.token_dim(layout),
            tokens: self.pairing.tokens(layout),
            d_model: self.d_model,
            heads: self.heads,
            layers: self.layers,
            d_ff: self.d_ff,
            time_features: self.time_features,
            sample_features: self.labels(),
        }
    }
}

/// The generative objective and its sampler.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum Objective {
    /// Flow Matching: velocity regression (the network predicting the velocity or the clean
    /// sample), Euler ODE sampler (or Heun).
    Fm {
        time: fm::TimeDistribution,
        solver: Solver,
        /// Files written before the choice existed predicted the velocity.
        #[serde(default)]
        prediction: path::Prediction,
    },
    /// MeanFlow: average velocity over an interval, regressed on a share `share` of samples
    /// with an interval (the rest plain FM), sampled in NFE equal jumps.
    MeanFlow {
        share: f32,
        #[serde(default)]
        prediction: path::Prediction,
        /// Files written before the choice existed used the MeanFlow identity.
        #[serde(default)]
        consistency: meanflow::Consistency,
    },
    /// DDPM on a cosine schedule of `steps` predicting `prediction`, ancestral sampling
    /// respaced to the NFE; clean predictions clipped to `clip` standard deviations.
    Ddpm {
        steps: usize,
        /// Files written before the choice existed predicted epsilon.
        #[serde(default = "ddpm::Prediction::epsilon")]
        prediction: ddpm::Prediction,
        clip: f32,
    },
}

impl Objective {
    /// Refuses settings the samplers cannot run.
    pub fn validate(&self) -> Result<(), String> {
        match *self {
            Objective::Fm { time: fm::TimeDistribution::LogitNormal { mean, std }, .. }
                if !(mean.is_finite() && std.is_finite() && std > 0.0) =>
            {
                Err(format!("logit-normal times need a finite mean and a positive std, not {mean} and {std}"))
            }
            Objective::Ddpm { steps, clip, .. }
                if !((1..=100_000).contains(&steps) && clip.is_finite() && clip > 0.0) =>
            {
                Err(format!("DDPM needs 1-100000 steps and a positive clip, not {steps} and {clip}"))
            }
            Objective::MeanFlow { share, .. } if !(0.0..=1.0).contains(&share) => {
                Err(format!("MeanFlow's share of intervals must be in [0, 1], not {share}"))
            }
            _ => Ok(()),
        }
    }

    pub fn name(&self) -> &'static str {
        match self {
            Objective::Fm { .. } => "fm",
            Objective::MeanFlow { .. } => "meanflow",
            Objective::Ddpm { .. } => "ddpm",
        }
    }

    /// The objective for people: its name in capitals, and what the network predicts where it
    /// is not the default (the clean sample for FM and MeanFlow, the noise for DDPM), and
    /// MeanFlow's interval splitting.
    pub fn label(&self) -> String {
        let name = self.name().to_uppercase();
        let notes: Vec<&str> = [
            (self.predicts_clean_flow(), "clean sample"),
            (matches!(self, Objective::MeanFlow { consistency: meanflow::Consistency::Split, .. }), "split"),
            (matches!(self, Objective::Ddpm { prediction: ddpm::Prediction::Epsilon, .. }), "epsilon"),
        ]
        .into_iter()
        .filter_map(|(holds, note)| holds.then_some(note))
        .collect();
        if notes.is_empty() { name } else { format!("{name} ({})", notes.join(", ")) }
    }

    /// Whether a flow network predicts the clean sample (see [`path::CleanSample`]).
    pub fn predicts_clean_flow(&self) -> bool {
        matches!(
            self,
            Objective::Fm { prediction: path::Prediction::Sample, .. }
                | Objective::MeanFlow { prediction: path::Prediction::Sample, .. }
        )
    }

    /// Noise levels the network takes per sample.
    pub fn times(&self) -> usize {
        match self {
            Objective::MeanFlow { .. } => 2,
            _ => 1,
        }
    }
}

/// Per-entry mean and standard deviation of an interleaved window.
#[derive(Clone, Debug, PartialEq)]
pub struct Normaliser {
    pub mean: Vec<f32>,
    pub std: Vec<f32>,
}

impl Normaliser {
    /// The dataset's moments, and mean 0, deviation 1 for the task label (taken as it is).
    pub fn new(layout: &TokenLayout, stats: &Stats) -> Self {
        let (at, labels) = (layout.label_at(), layout.labels);
        let with_label = |mut v: Vec<f32>, fill: f32| {
            v.splice(at..at, std::iter::repeat_n(fill, labels));
            v
        };
        Self {
            mean: with_label(layout.interleave(&stats.state_mean, &stats.action_mean), 0.0),
            std: with_label(layout.interleave(&stats.state_std, &stats.action_std), 1.0),
        }
    }

    /// Normalises rows whose entries start at `offset` of the window.
    pub fn normalise(&self, x: &mut [f32], offset: usize, width: usize) {
        for row in x.chunks_exact_mut(width) {
            for (j, v) in row.iter_mut().enumerate() {
                *v = (*v - self.mean[offset + j]) / self.std[offset + j];
            }
        }
    }

    pub fn denormalise(&self, x: &mut [f32], offset: usize, width: usize) {
        for row in x.chunks_exact_mut(width) {
            for (j, v) in row.iter_mut().enumerate() {
                *v = *v * self.std[offset + j] + self.mean[offset + j];
            }
        }
    }
}

/// The network with its token layout, in normalised units.
#[derive(Clone, Debug)]
pub struct TrajectoryNet {
    pub layout: TokenLayout,
    pub pairing: Pairing,
    pub net: Transformer,
    /// The window entry each token entry holds ([`Pairing::gather`]).
    gather: Vec<Option<usize>>,
    /// For each window entry, the token entry the network predicts it in (the first holding it).
    own: Vec<usize>,
}

impl TrajectoryNet {
    pub fn new(layout: TokenLayout, pairing: Pairing, net: Transformer) -> Self {
        let gather = pairing.gather(&layout);
        let mut own = vec![usize::MAX; layout.window_len()];
        for (p, j) in gather.iter().enumerate().rev() {
            if let Some(j) = *j {
                own[j] = p;
            }
        }
        Self { layout, pairing, net, gather, own }
    }

    /// Tokens of `concat(cond_i, x_i)` for each sample, as the pairing cuts them.
    pub fn tokens(&self, x: &[f32], cond: &[f32], n: usize) -> Vec<f32> {
        let (c, f) = (self.layout.cond_len(), self.layout.future_len());
        assert_eq!(x.len(), n * f, "future has the wrong length");
        assert_eq!(cond.len(), n * c, "conditioning has the wrong length");
        let mut out = Vec::with_capacity(n * self.gather.len());
        for i in 0..n {
            let at = |j: usize| if j < c { cond[i * c + j] } else { x[i * f + j - c] };
            out.extend(self.gather.iter().map(|j| j.map_or(0.0, at)));
        }
        out
    }

    /// The Transformer's forward pass over `concat(cond, x)`, kept for a backward pass; a
    /// labelled model's label joins the noise level's embedding, added to every token.
    pub fn forward(&self, x: &[f32], t: &[f32], cond: &[f32], n: usize) -> flowmimic_nn::transformer::Tape {
        let labels = self.layout.label_range();
        let own: Vec<f32> =
            cond.chunks_exact(self.layout.cond_len()).flat_map(|row| &row[labels.clone()]).copied().collect();
        self.net.forward_with(&self.tokens(x, cond, n), &network_times(t, n), &own, n)
    }

    /// The future part of each sample's output tokens, each entry read from its own token.
    pub fn future(&self, output: &[f32]) -> Vec<f32> {
        let c = self.layout.cond_len();
        output.chunks_exact(self.gather.len()).flat_map(|row| self.own[c..].iter().map(|&p| row[p])).collect()
    }

    /// A cotangent of the future (n x future) as one of the output tokens: zero on the
    /// conditioning, the padding and the entries that are not read back.
    pub fn output_cotangent(&self, d_future: &[f32], n: usize) -> Vec<f32> {
        let (c, f) = (self.layout.cond_len(), self.layout.future_len());
        let mut out = vec![0.0; n * self.gather.len()];
        for (i, row) in out.chunks_exact_mut(self.gather.len()).enumerate() {
            for (j, &p) in self.own[c..].iter().enumerate() {
                row[p] = d_future[i * f + j];
            }
        }
        out
    }

    /// A gradient on the input tokens as one on the future (n x future): the sum over every
    /// token entry that holds a future entry.
    pub fn future_gradient(&self, d_tokens: &[f32]) -> Vec<f32> {
        let (c, f) = (self.layout.cond_len(), self.layout.future_len());
        let mut out = Vec::new();
        for row in d_tokens.chunks_exact(self.gather.len()) {
            let mut g = vec![0.0; f];
            for (p, j) in self.gather.iter().enumerate() {
                if let Some(j) = j.filter(|&j| j >= c) {
                    g[j - c] += row[p];
                }
            }
            out.extend(g);
        }
        out
    }

    /// For each entry of a sample's tokens, the entry of `concat(cond, x)` it holds (`None`:
    /// zero padding): how an exported graph builds the tokens.
    pub fn token_sources(&self) -> &[Option<usize>] {
        &self.gather
    }

    /// For each entry of `concat(cond, x)`, the token entry the network predicts it in: how an
    /// exported graph reads the future back.
    pub fn output_entries(&self) -> &[usize] {
        &self.own
    }
}

/// Noise levels as the Transformer takes them. Its time features are sinusoids of `1000 t`, up
/// to 1000 rad per unit of time; MeanFlow's target differentiates the network along the path,
/// and at that rate the derivative of an untrained network is of order 1000 and training
/// diverges (measured with the `tiny` preset: loss 429 -> 3,211 in 200 steps). So a network of
/// two times (MeanFlow's) takes them in hundredths ([`TWO_TIMES_SCALE`]), at most 10 rad per
/// unit (loss 1.95 -> 1.75).
fn network_times(t: &[f32], n: usize) -> std::borrow::Cow<'_, [f32]> {
    if t.len() == 2 * n { t.iter().map(|t| TWO_TIMES_SCALE * t).collect::<Vec<f32>>().into() } else { t.into() }
}

/// The factor on the times of a network of two times per sample (MeanFlow's).
pub const TWO_TIMES_SCALE: f32 = 0.01;

impl Network for TrajectoryNet {
    fn dim(&self) -> usize {
        self.layout.future_len()
    }

    fn predict(&self, x: &[f32], t: &[f32], cond: &[f32], n: usize) -> Vec<f32> {
        self.future(&self.forward(x, t, cond, n).output)
    }

    fn predict_pullback(
        &self,
        x: &[f32],
        t: &[f32],
        cond: &[f32],
        n: usize,
        cotangent: &mut dyn FnMut(&[f32]) -> Vec<f32>,
    ) -> (Vec<f32>, Vec<f32>) {
        let tape = self.forward(x, t, cond, n);
        let y = self.future(&tape.output);
        let u = cotangent(&y);
        let d_input = self.net.input_grad(&tape, &self.output_cotangent(&u, n));
        (y, self.future_gradient(&d_input))
    }
}

/// Classifier-free guidance on a labelled network's label: the prediction told nothing (the
/// label's entries zero, as training left it out in `label_dropout` of its windows) moved
/// `scale` times the way the label moves it, `u + scale (c - u)`. Both predictions run in one
/// batch of 2n rows.
struct Told<'a> {
    net: &'a dyn Network,
    scale: f32,
    cond_len: usize,
    labels: std::ops::Range<usize>,
}

/// Conditioning rows of `cond_len` told nothing: their `labels` entries zeroed.
fn untell(cond: &mut [f32], cond_len: usize, labels: &std::ops::Range<usize>) {
    cond.chunks_exact_mut(cond_len).for_each(|row| row[labels.clone()].fill(0.0));
}

impl Told<'_> {
    /// The rows twice over: first told nothing, then as given.
    fn doubled(&self, x: &[f32], t: &[f32], cond: &[f32]) -> (Vec<f32>, Vec<f32>, Vec<f32>) {
        let mut untold = cond.to_vec();
        untell(&mut untold, self.cond_len, &self.labels);
        untold.extend_from_slice(cond);
        ([x, x].concat(), [t, t].concat(), untold)
    }

    fn combine(&self, both: &[f32]) -> Vec<f32> {
        let (u, c) = both.split_at(both.len() / 2);
        u.iter().zip(c).map(|(u, c)| u + self.scale * (c - u)).collect()
    }
}

impl Network for Told<'_> {
    fn dim(&self) -> usize {
        self.net.dim()
    }

    fn predict(&self, x: &[f32], t: &[f32], cond: &[f32], n: usize) -> Vec<f32> {
        let (x, t, cond) = self.doubled(x, t, cond);
        self.combine(&self.net.predict(&x, &t, &cond, 2 * n))
    }

    /// `y = (1 - s) u + s c`, so `(dy/dx)^T g = (1 - s) (du/dx)^T g + s (dc/dx)^T g`.
    fn predict_pullback(
        &self,
        x: &[f32],
        t: &[f32],
        cond: &[f32],
        n: usize,
        cotangent: &mut dyn FnMut(&[f32]) -> Vec<f32>,
    ) -> (Vec<f32>, Vec<f32>) {
        let (xx, tt, cc) = self.doubled(x, t, cond);
        let mut y = Vec::new();
        let (_, pulled) = self.net.predict_pullback(&xx, &tt, &cc, 2 * n, &mut |both| {
            y = self.combine(both);
            let g = cotangent(&y);
            g.iter().map(|g| (1.0 - self.scale) * g).chain(g.iter().map(|g| self.scale * g)).collect()
        });
        let (gu, gc) = pulled.split_at(pulled.len() / 2);
        (y, gu.iter().zip(gc).map(|(a, b)| a + b).collect())
    }
}

/// A trained model: network, normalisation and objective.
#[derive(Clone, Debug)]
pub struct TrajectoryModel {
    pub config: ModelConfig,
    pub objective: Objective,
    pub net: TrajectoryNet,
    pub stats: Stats,
    pub norm: Normaliser,
    /// An inverse-dynamics model fitted to the same data, when the model directory holds one
    /// ([`crate::inverse`]): the controller may execute its action for the plan's next state.
    pub inverse: Option<InverseDynamics>,
}

/// Guidance in physical units: `grad` is the task cost's gradient at predicted clean futures
/// (n x future, physical units); the model maps it to its normalised space.
pub struct TaskGuidance<'a> {
    pub weight: f32,
    pub grad: &'a (dyn Fn(&[f32], usize) -> Vec<f32> + Sync),
    pub steps: std::ops::Range<usize>,
    pub gradient: Gradient,
}

impl TrajectoryModel {
    /// A freshly initialised model (weights drawn from `seed`) normalising with `stats`.
    pub fn new(layout: TokenLayout, config: ModelConfig, objective: Objective, stats: Stats, seed: u64) -> Self {
        let net = Transformer::new(config.transformer(&layout), &mut StdRng::seed_from_u64(seed));
        let norm = Normaliser::new(&layout, &stats);
        Self { config, objective, net: TrajectoryNet::new(layout, config.pairing, net), stats, norm, inverse: None }
    }

    pub fn layout(&self) -> &TokenLayout {
        &self.net.layout
    }

    /// Samples futures (n x future, physical units) given conditionings (n x cond, physical
    /// units, as [`TokenLayout::conditioning`] of the history's states and actions) with `nfe`
    /// network evaluations; with guidance, its gradient is taken as `guidance.gradient` says.
    pub fn sample(
        &self,
        cond: &[f32],
        n: usize,
        nfe: usize,
        guidance: Option<&TaskGuidance>,
        rng: &mut impl Rng,
    ) -> Vec<f32> {
        self.sample_told(cond, n, nfe, 1.0, guidance, rng)
    }

    /// [`TrajectoryModel::sample`], a labelled model's label weighed by `label_scale`
    /// (classifier-free guidance, [`Told`]): 0 samples as if told nothing, 1 as told, above 1
    /// past it, at two network calls' cost.
    pub fn sample_told(
        &self,
        cond: &[f32],
        n: usize,
        nfe: usize,
        label_scale: f32,
        guidance: Option<&TaskGuidance>,
        rng: &mut impl Rng,
    ) -> Vec<f32> {
        let (c, f) = (self.layout().cond_len(), self.layout().future_len());
        let mut cond = cond.to_vec();
        self.norm.normalise(&mut cond, 0, c);
        // The cost sees physical units; by the chain rule its normalised gradient is std * grad.
        let normalised_grad = |x: &[f32], n: usize| -> Vec<f32> {
            let mut physical = x.to_vec();
            self.norm.denormalise(&mut physical, c, f);
            let g = (guidance.expect("only called with guidance").grad)(&physical, n);
            g.chunks_exact(f).flat_map(|row| row.iter().enumerate().map(|(j, g)| g * self.norm.std[c + j])).collect()
        };
        let inner = guidance.map(|g| Guidance {
            weight: g.weight,
            grad: &normalised_grad,
            steps: g.steps.clone(),
            gradient: g.gradient,
        });
        let noise: Vec<f32> = (0..n * f).map(|_| StandardNormal.sample(rng)).collect();
        let labels = self.layout().label_range();
        let mut x = match label_scale {
            1.0 => self.sample_from(&cond, noise, n, nfe, inner.as_ref(), rng),
            0.0 => {
                untell(&mut cond, c, &labels);
                self.sample_from(&cond, noise, n, nfe, inner.as_ref(), rng)
            }
            scale => {
                let told = Told { net: &self.net, scale, cond_len: c, labels };
                self.sample_with(&told, &cond, noise, n, nfe, inner.as_ref(), rng)
            }
        };
        self.norm.denormalise(&mut x, c, f);
        x
    }

    /// Samples futures from `noise` (n x future) given normalised conditionings, in normalised
    /// units, with the objective's sampler at `nfe` (DDPM's ancestral steps draw from `rng`).
    pub fn sample_from(
        &self,
        cond: &[f32],
        noise: Vec<f32>,
        n: usize,
        nfe: usize,
        guidance: Option<&Guidance>,
        rng: &mut impl Rng,
    ) -> Vec<f32> {
        self.sample_with(&self.net, cond, noise, n, nfe, guidance, rng)
    }

    /// [`TrajectoryModel::sample_from`] with `net` in place of the model's own network.
    #[allow(clippy::too_many_arguments)]
    fn sample_with(
        &self,
        net: &dyn Network,
        cond: &[f32],
        noise: Vec<f32>,
        n: usize,
        nfe: usize,
        guidance: Option<&Guidance>,
        rng: &mut impl Rng,
    ) -> Vec<f32> {
        match self.objective {
            Objective::Fm { solver, .. } => {
                self.as_flow(net, |net| fm::sample(net, cond, noise, n, nfe, solver, guidance))
            }
            Objective::MeanFlow { .. } => self.as_flow(net, |net| meanflow::sample(net, cond, noise, n, nfe, guidance)),
            Objective::Ddpm { steps, prediction, clip } => {
                let schedule = ddpm::Schedule::cosine(steps);
                ddpm::sample(net, &schedule, prediction, cond, noise, n, nfe, clip, guidance, rng)
            }
        }
    }

    /// Runs `f` on the network as Flow Matching's and MeanFlow's samplers and MeanFlow's target
    /// read it: as a velocity, through [`path::CleanSample`] when it predicts the clean sample.
    pub(crate) fn with_flow_net<R>(&self, f: impl FnOnce(&dyn Network) -> R) -> R {
        self.as_flow(&self.net, f)
    }

    /// [`TrajectoryModel::with_flow_net`] on `net`, the model's network or one built on it.
    fn as_flow<R>(&self, net: &dyn Network, f: impl FnOnce(&dyn Network) -> R) -> R {
        if self.objective.predicts_clean_flow() { f(&path::CleanSample(net)) } else { f(net) }
    }

    /// Network FLOPs of one sampling call for `n` samples at `nfe`.
    pub fn sample_flops(&self, n: usize, nfe: usize) -> f64 {
        self.net.net.flops_per_sample() * (n * nfe) as f64
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::Gradient;
    use crate::guidance::guided_prediction;

    /// A small network with random weights everywhere, so every path of the pullback counts.
    fn small_net(pairing: Pairing) -> TrajectoryNet {
        small_net_labelled(pairing, false, false)
    }

    fn small_net_labelled(pairing: Pairing, task_labels: bool, command_labels: bool) -> TrajectoryNet {
        let config = ModelConfig {
            history: 1,
            horizon: 2,
            d_model: 8,
            heads: 2,
            layers: 2,
            d_ff: 12,
            time_features: 4,
            pairing,
            task_labels,
            command_labels,
            command_steps: 0,
        };
        let spec = WindowSpec { history: 1, horizon: 2 };
        let layout = TokenLayout { state_dim: 3, action_dim: 2, spec, labels: config.labels() };
        let mut rng = StdRng::seed_from_u64(4);
        let mut net = Transformer::new(config.transformer(&layout), &mut rng);
        net.params.iter_mut().for_each(|p| *p += 0.4 * rng.random::<f32>() - 0.2);
        TrajectoryNet::new(layout, config.pairing, net)
    }

    #[test]
    fn tokens_hold_the_conditioning_and_future_in_window_order_and_future_reads_them_back() {
        let pairings = [Pairing::StateAction, Pairing::ActionState, Pairing::StateActionState];
        for (pairing, len) in pairings.into_iter().zip([20, 25, 32]) {
            let net = small_net(pairing);
            let (c, f) = (net.layout.cond_len(), net.layout.future_len());
            let cond: Vec<f32> = (0..2 * c).map(|i| 100.0 + i as f32).collect();
            let x: Vec<f32> = (0..2 * f).map(|i| -(i as f32) - 1.0).collect();
            let tokens = net.tokens(&x, &cond, 2);
            assert_eq!(tokens.len(), 2 * len, "{pairing:?}");
            assert_eq!(net.future(&tokens), x, "{pairing:?}");
            // Reading back and spreading a cotangent are each other's transposes on own slots.
            assert_eq!(net.future(&net.output_cotangent(&x, 2)), x, "{pairing:?}");
            let first = &tokens[..len];
            match pairing {
                // [padding action, s_{t-1}], ..., [a_{t+H}, padding state].
                Pairing::ActionState => assert!(first[..2] == [0.0; 2] && first[2] == 100.0 && first[22..] == [0.0; 3]),
                // [s_{t-1}, a_{t-1}, s_t]: s_t is the conditioning's entries 5-7.
                Pairing::StateActionState => assert!(first[5..8] == [105.0, 106.0, 107.0] && first[29..] == [0.0; 3]),
                Pairing::StateAction => {
                    assert_eq!(first, &cond[..c].iter().chain(&x[..f]).copied().collect::<Vec<_>>())
                }
            }
        }
    }

    #[test]
    fn a_task_label_sits_after_s_t_and_joins_the_noise_levels_embedding() {
        for pairing in [Pairing::StateAction, Pairing::ActionState, Pairing::StateActionState] {
            let (plain, labelled) = (small_net(pairing), small_net_labelled(pairing, true, false));
            let (c, f) = (labelled.layout.cond_len(), labelled.layout.future_len());
            assert_eq!((c, f), (plain.layout.cond_len() + 2, plain.layout.future_len()), "{pairing:?}");
            let states: Vec<f32> = (0..12).map(|i| i as f32).collect();
            let actions: Vec<f32> = (0..8).map(|i| 100.0 + i as f32).collect();
            let reach = Some(Label::Task(TaskLabel::Reach));
            let window = labelled.layout.window(&states, &actions, reach);
            let cond = labelled.layout.conditioning(&states[..6], &actions[..2], reach);
            assert_eq!(window[..c], cond[..], "{pairing:?}");
            assert_eq!(cond[c - 2..], [0.0, 1.0], "{pairing:?}");
            assert_eq!(labelled.layout.current_state(&cond), &states[3..6], "{pairing:?}");
            assert_eq!(labelled.layout.label(None), [0.0, 0.0]);
            // The tokens are the unlabelled network's; the label moves the output through the
            // noise level's embedding, which every token adds.
            let plain_cond = plain.layout.interleave(&states[..6], &actions[..2]);
            let x = &window[c..];
            let tokens = labelled.tokens(x, &cond, 1);
            assert_eq!(tokens, plain.tokens(x, &plain_cond, 1), "{pairing:?}");
            assert_eq!(labelled.future(&tokens), x, "{pairing:?}");
            assert_eq!(labelled.net.config.sample_features, 2);
            let walk = labelled.layout.conditioning(&states[..6], &actions[..2], Some(Label::Task(TaskLabel::Walk)));
            let (told, other) = (labelled.predict(x, &[0.3], &cond, 1), labelled.predict(x, &[0.3], &walk, 1));
            assert!(told.iter().zip(&other).all(|(a, b)| a != b), "{pairing:?}: every entry hears the label");
        }
    }

    #[test]
    fn a_command_label_says_it_is_given_and_a_label_of_the_other_kind_says_nothing() {
        let net = small_net_labelled(Pairing::StateActionState, false, true);
        let layout = net.layout;
        assert_eq!(layout.labels, Label::COMMAND);
        assert_eq!(layout.label(Some(Label::Command([0.8, -0.1, 0.6]))), [1.0, 0.8, -0.1, 0.6]);
        // Standing still asked is told apart from nothing asked.
        assert_eq!(layout.label(Some(Label::Command([0.0; 3]))), [1.0, 0.0, 0.0, 0.0]);
        assert_eq!(layout.label(None), [0.0; 4]);
        assert_eq!(layout.label(Some(Label::Task(TaskLabel::Walk))), [0.0; 4]);
        let tasked = small_net_labelled(Pairing::StateActionState, true, false).layout;
        assert_eq!(tasked.label(Some(Label::Command([0.8, 0.0, 0.0]))), [0.0; 2]);
        let config = ModelConfig { task_labels: true, command_labels: true, ..ModelConfig::default() };
        assert!(config.validate().unwrap_err().contains("one kind of label"));
    }

    #[test]
    fn guidance_through_the_network_is_the_gradient_of_the_cost_of_the_clean_estimate() {
        for pairing in [Pairing::StateAction, Pairing::ActionState, Pairing::StateActionState] {
            let net = small_net(pairing);
            guidance_matches_finite_differences(&net, &net.layout);
        }
        // A network predicting the clean sample, read as a velocity.
        let net = small_net(Pairing::StateAction);
        guidance_matches_finite_differences(&crate::path::CleanSample(&net), &net.layout);
    }

    /// Told at scale 1 a labelled network predicts as given, at 0 as with its label zeroed, and
    /// in between and beyond on the line through both; guidance through it is still the
    /// gradient of the cost of its clean estimate.
    #[test]
    fn a_label_weighed_by_classifier_free_guidance() {
        let net = small_net_labelled(Pairing::StateActionState, false, true);
        let layout = net.layout;
        let (n, f, c) = (2, layout.future_len(), layout.cond_len());
        let x: Vec<f32> = (0..n * f).map(|i| (i as f32 * 0.7).sin()).collect();
        let mut cond: Vec<f32> = (0..n * c).map(|i| (i as f32 * 0.3).cos()).collect();
        let t = vec![0.4; n];
        let told = net.predict(&x, &t, &cond, n);
        let told_as = |scale| Told { net: &net, scale, cond_len: c, labels: layout.label_range() };
        let half = told_as(0.5).predict(&x, &t, &cond, n);
        let twice = told_as(2.0).predict(&x, &t, &cond, n);
        let same = told_as(1.0).predict(&x, &t, &cond, n);
        untell(&mut cond, c, &layout.label_range());
        let untold = net.predict(&x, &t, &cond, n);
        for j in 0..told.len() {
            let (u, c) = (untold[j], told[j]);
            assert!((same[j] - c).abs() < 1e-5 && (half[j] - 0.5 * (u + c)).abs() < 1e-5, "{j}");
            assert!((twice[j] - (2.0 * c - u)).abs() < 1e-4, "{j}");
        }
        assert!(told.iter().zip(&untold).any(|(a, b)| (a - b).abs() > 1e-3), "the label moves the prediction");
        guidance_matches_finite_differences(&told_as(2.0), &layout);
    }

    fn guidance_matches_finite_differences(net: &dyn Network, layout: &TokenLayout) {
        let (n, f, c) = (2, layout.future_len(), layout.cond_len());
        let x: Vec<f32> = (0..n * f).map(|i| (i as f32 * 0.7).sin()).collect();
        let cond: Vec<f32> = (0..n * c).map(|i| (i as f32 * 0.3).cos()).collect();
        let t = vec![0.4; n];
        let target: Vec<f32> = (0..n * f).map(|i| (i as f32 * 0.2).cos()).collect();
        // G(x_hat) = 1/2 |x_hat - target|^2; FM's clean estimate x_hat = x + (1 - s) v(x), and
        // DDPM's epsilon form x_hat = (x - sqrt(1 - abar) eps(x)) / sqrt(abar).
        let grad = |x_hat: &[f32], _n: usize| -> Vec<f32> { x_hat.iter().zip(&target).map(|(a, b)| a - b).collect() };
        for (a, b) in [(1.0, 0.6), (1.25, -0.75)] {
            let cost = |x: &[f32]| -> f64 {
                let y = net.predict(x, &t, &cond, n);
                x.iter().zip(&y).zip(&target).map(|((x, y), g)| 0.5 * f64::from(a * x + b * y - g).powi(2)).sum()
            };
            let guidance = Guidance { weight: 1.0, grad: &grad, steps: 0..1, gradient: Gradient::ThroughNetwork };
            let (_, through) = guided_prediction(net, &x, &t, &cond, n, (a, b), Some(&guidance), 0);
            let through = through.unwrap();
            let eps = 1e-2;
            for k in 0..x.len() {
                let (mut plus, mut minus) = (x.clone(), x.clone());
                plus[k] += eps;
                minus[k] -= eps;
                let fd = (cost(&plus) - cost(&minus)) / (2.0 * f64::from(eps));
                let g = f64::from(through[k]);
                assert!((fd - g).abs() < 2e-2 * (1.0 + fd.abs()), "({a}, {b}) x[{k}]: fd {fd} vs {g}");
            }
            // The cost-only gradient differs: it leaves out the network's Jacobian.
            let guidance = Guidance { gradient: Gradient::CostOnly, ..guidance };
            let (_, only) = guided_prediction(net, &x, &t, &cond, n, (a, b), Some(&guidance), 0);
            assert!(only.unwrap().iter().zip(&through).any(|(p, q)| (p - q).abs() > 1e-3));
        }
    }
}

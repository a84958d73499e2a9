//! PPO as rsl_rl (BeyondMimic's trainer) runs it: Gaussian policy with a learned
//! state-independent log-std, clipped surrogate, clipped value loss, entropy bonus, GAE,
//! advantage normalisation, global gradient-norm clipping and an adaptive-KL learning rate.
//! Gradients of the losses with respect to the network outputs are written out analytically
//! ([`minibatch_loss`], checked against finite differences). Its settings are [`TrackConfig`]'s.

use crate::TrackConfig;
use flowmimic_nn::{Adam, Mlp};
use rand::Rng;
use rand::seq::SliceRandom;
use rand_distr::{Distribution, StandardNormal};

/// Running mean and variance of observations (merged batch by batch).
#[derive(Clone, Debug)]
pub struct Normaliser {
    pub mean: Vec<f64>,
    pub var: Vec<f64>,
    pub count: f64,
}

impl Normaliser {
    pub fn new(dim: usize) -> Self {
        Self { mean: vec![0.0; dim], var: vec![1.0; dim], count: 1e-4 }
    }

    pub fn update(&mut self, rows: &[f32]) {
        let d = self.mean.len();
        let n = (rows.len() / d) as f64;
        if n == 0.0 {
            return;
        }
        for j in 0..d {
            let col = rows.iter().skip(j).step_by(d).map(|&x| f64::from(x));
            let m = col.clone().sum::<f64>() / n;
            let v = col.map(|x| (x - m).powi(2)).sum::<f64>() / n;
            let total = self.count + n;
            let delta = m - self.mean[j];
            self.mean[j] += delta * n / total;
            self.var[j] = (self.var[j] * self.count + v * n + delta * delta * self.count * n / total) / total;
        }
        self.count += n;
    }

    pub fn apply(&self, rows: &mut [f32]) {
        let d = self.mean.len();
        for row in rows.chunks_mut(d) {
            for (j, x) in row.iter_mut().enumerate() {
                *x = ((f64::from(*x) - self.mean[j]) / (self.var[j] + 1e-8).sqrt()).clamp(-5.0, 5.0) as f32;
            }
        }
    }
}

/// Actor, critic, log-std and observation statistics.
#[derive(Clone, Debug)]
pub struct Policy {
    pub actor: Mlp,
    pub critic: Mlp,
    pub log_std: Vec<f32>,
    pub normaliser: Normaliser,
}

impl Policy {
    pub fn new(obs: usize, act: usize, cfg: &TrackConfig, rng: &mut impl Rng) -> Self {
        let sizes = |out| [&[obs][..], &cfg.hidden, &[out]].concat();
        Self {
            actor: Mlp::new(&sizes(act), 0.01, rng),
            critic: Mlp::new(&sizes(1), 1.0, rng),
            log_std: vec![cfg.init_log_std as f32; act],
            normaliser: Normaliser::new(obs),
        }
    }

    /// Observation entries the policy reads.
    pub fn obs_dim(&self) -> usize {
        self.actor.inputs()
    }

    /// This policy reading more observation entries, one per index of `counterparts`, with
    /// zero weights (it acts and values states as before) and the statistics of the entry it
    /// names, so that the new entries start normalised.
    pub fn widened(mut self, counterparts: &[usize]) -> Self {
        self.actor.widen_inputs(counterparts.len());
        self.critic.widen_inputs(counterparts.len());
        let n = &mut self.normaliser;
        for &j in counterparts {
            let (mean, var) = (n.mean[j], n.var[j]);
            n.mean.push(mean);
            n.var.push(var);
        }
        self
    }

    /// Flat parameters: actor, critic, log-std.
    pub fn params(&self) -> Vec<f32> {
        [self.actor.params(), self.critic.params(), self.log_std.clone()].concat()
    }

    pub fn set_params(&mut self, p: &[f32]) {
        let (a, c) = (self.actor.num_params(), self.critic.num_params());
        self.actor.set_params(&p[..a]);
        self.critic.set_params(&p[a..a + c]);
        self.log_std.copy_from_slice(&p[a + c..]);
    }

    pub fn num_params(&self) -> usize {
        self.actor.num_params() + self.critic.num_params() + self.log_std.len()
    }

    /// Normalised copies of raw observations.
    pub fn normalise(&self, raw: &[f32]) -> Vec<f32> {
        let mut x = raw.to_vec();
        self.normaliser.apply(&mut x);
        x
    }

    /// Deterministic actions (the mean) for raw observations.
    pub fn act(&self, raw: &[f32], n: usize) -> Vec<f32> {
        self.actor.predict(&self.normalise(raw), n)
    }
}

/// Log-density of `u` under a diagonal Gaussian; `inv_std` is `exp(-log_std)`, computed once per
/// batch (an `exp` per element was a visible share of the update).
fn log_prob(u: &[f32], mean: &[f32], log_std: &[f32], inv_std: &[f32]) -> f32 {
    let mut sum = 0.0;
    for j in 0..u.len() {
        let z = (u[j] - mean[j]) * inv_std[j];
        sum += -0.5 * z * z - log_std[j] - 0.918_938_5;
    }
    sum
}

fn inverse_std(log_std: &[f32]) -> Vec<f32> {
    log_std.iter().map(|s| (-s).exp()).collect()
}

/// The transitions of one PPO iteration, `steps x envs` (row-major: step, then env): what the
/// update learns from (not a rollout file, `flowmimic_control::Rollout`).
pub struct RolloutBuffer {
    pub envs: usize,
    pub obs: Vec<f32>,
    pub actions: Vec<f32>,
    pub log_probs: Vec<f32>,
    /// The policy's means when acting, and its log-std then (for the KL of the update).
    pub means: Vec<f32>,
    pub log_std: Vec<f32>,
    pub values: Vec<f32>,
    pub rewards: Vec<f32>,
    /// The episode ended after this transition (failure or time limit).
    pub dones: Vec<bool>,
    /// The critic's values of the observations after the last step.
    pub last_values: Vec<f32>,
}

/// What the policy did for a batch of observations.
pub struct Sampled {
    pub actions: Vec<f32>,
    pub means: Vec<f32>,
    pub log_probs: Vec<f32>,
    pub values: Vec<f32>,
}

/// Samples actions for normalised observations.
pub fn sample(policy: &Policy, obs: &[f32], n: usize, rng: &mut impl Rng) -> Sampled {
    let (mean, values) = rayon::join(|| policy.actor.predict(obs, n), || policy.critic.predict(obs, n));
    let act = policy.log_std.len();
    let std: Vec<f32> = policy.log_std.iter().map(|s| s.exp()).collect();
    let inv_std = inverse_std(&policy.log_std);
    let mut actions = mean.clone();
    for row in actions.chunks_mut(act) {
        for (a, s) in row.iter_mut().zip(&std) {
            let z: f32 = StandardNormal.sample(rng);
            *a += s * z;
        }
    }
    let log_probs = (0..n)
        .map(|i| {
            let (u, m) = (&actions[i * act..(i + 1) * act], &mean[i * act..(i + 1) * act]);
            log_prob(u, m, &policy.log_std, &inv_std)
        })
        .collect();
    Sampled { actions, means: mean, log_probs, values }
}

/// GAE advantages and returns.
pub fn advantages(r: &RolloutBuffer, gamma: f32, lambda: f32) -> (Vec<f32>, Vec<f32>) {
    let e = r.envs;
    let steps = r.rewards.len() / e;
    let mut adv = vec![0.0; r.rewards.len()];
    let mut next_adv = vec![0.0; e];
    for t in (0..steps).rev() {
        for i in 0..e {
            let k = t * e + i;
            let next_v = if t + 1 < steps { r.values[k + e] } else { r.last_values[i] };
            let live = if r.dones[k] { 0.0 } else { 1.0 };
            let delta = r.rewards[k] + gamma * live * next_v - r.values[k];
            next_adv[i] = delta + gamma * lambda * live * next_adv[i];
            adv[k] = next_adv[i];
        }
    }
    let returns = adv.iter().zip(&r.values).map(|(a, v)| a + v).collect();
    (adv, returns)
}

/// Losses and diagnostics of one update.
#[derive(Clone, Copy, Debug, Default, serde::Serialize)]
pub struct UpdateStats {
    pub surrogate: f32,
    pub value_loss: f32,
    pub entropy: f32,
    pub kl: f32,
    pub clip_fraction: f32,
    pub learning_rate: f32,
}

/// Optimiser state that persists across iterations.
pub struct Optimiser {
    pub adam: Adam,
    pub lr: f32,
}

/// One minibatch at the networks' outputs: the actor's means and the critic's values (one row
/// per sample), and what was recorded when acting.
pub struct Minibatch<'a> {
    pub means: &'a [f32],
    pub values: &'a [f32],
    pub actions: &'a [f32],
    pub old_log_probs: &'a [f32],
    pub advantages: &'a [f32],
    pub old_values: &'a [f32],
    pub returns: &'a [f32],
}

/// PPO's minibatch loss, `surrogate + value_coef * value_loss - entropy * H`, with its terms
/// and its gradient with respect to the means, the values and the log-std: what the update
/// backpropagates through the networks.
pub struct MinibatchLoss {
    /// The clipped surrogate (to minimise) and the clipped value loss, means over the batch.
    pub surrogate: f32,
    pub value_loss: f32,
    /// The share of samples whose ratio the clip held.
    pub clipped: f32,
    pub g_mean: Vec<f32>,
    pub g_value: Vec<f32>,
    pub g_log_std: Vec<f32>,
}

/// The loss of one minibatch and its gradients, written out (as rsl_rl computes them).
pub fn minibatch_loss(b: &Minibatch, log_std: &[f32], cfg: &TrackConfig) -> MinibatchLoss {
    let (act, mb) = (log_std.len(), b.values.len());
    let (clip, eps_v) = (cfg.clip as f32, cfg.clip as f32);
    let mut g_mean = vec![0.0f32; mb * act];
    let mut g_value = vec![0.0f32; mb];
    let mut g_log_std = vec![0.0f32; act];
    let (mut surr, mut vloss, mut clipped) = (0.0, 0.0, 0.0);
    let inv = 1.0 / mb as f32;
    let inv_std = inverse_std(log_std);
    for row in 0..mb {
        let m = &b.means[row * act..(row + 1) * act];
        let u = &b.actions[row * act..(row + 1) * act];
        let ratio = (log_prob(u, m, log_std, &inv_std) - b.old_log_probs[row]).exp();
        let a = b.advantages[row];
        let unclipped = ratio * a;
        let clipped_obj = ratio.clamp(1.0 - clip, 1.0 + clip) * a;
        surr += -unclipped.min(clipped_obj) * inv;
        // d(-min)/d logp = -ratio * a where the unclipped term is the minimum.
        let active = unclipped <= clipped_obj;
        clipped += if active { 0.0 } else { inv };
        let g_logp = if active { -ratio * a * inv } else { 0.0 };
        for j in 0..act {
            let z = (u[j] - m[j]) * inv_std[j];
            g_mean[row * act + j] = g_logp * z * inv_std[j];
            g_log_std[j] += g_logp * (z * z - 1.0);
        }
        // Clipped value loss (coefficient cfg.value_coef), as rsl_rl.
        let v = b.values[row];
        let (v_old, ret) = (b.old_values[row], b.returns[row]);
        let v_clipped = v_old + (v - v_old).clamp(-eps_v, eps_v);
        let (l1, l2) = ((v - ret).powi(2), (v_clipped - ret).powi(2));
        vloss += l1.max(l2) * inv;
        let inside = (v - v_old).abs() <= eps_v;
        g_value[row] = cfg.value_coef as f32 * if l1 >= l2 || inside { 2.0 * (v - ret) } else { 0.0 } * inv;
    }
    // Entropy bonus: d(-c H)/d log_std = -c per dimension.
    for g in &mut g_log_std {
        *g -= cfg.entropy as f32;
    }
    MinibatchLoss { surrogate: surr, value_loss: vloss, clipped, g_mean, g_value, g_log_std }
}

/// The PPO update over one rollout.
pub fn update(
    policy: &mut Policy,
    opt: &mut Optimiser,
    r: &RolloutBuffer,
    cfg: &TrackConfig,
    rng: &mut impl Rng,
) -> UpdateStats {
    let (gamma, lambda) = (cfg.gamma as f32, cfg.lambda as f32);
    let n = r.rewards.len();
    let obs_dim = r.obs.len() / n;
    let act = policy.log_std.len();
    let (adv, returns) = advantages(r, gamma, lambda);
    let mean = adv.iter().sum::<f32>() / adv.len() as f32;
    let std = (adv.iter().map(|a| (a - mean).powi(2)).sum::<f32>() / adv.len() as f32).sqrt() + 1e-8;
    let adv: Vec<f32> = adv.iter().map(|a| (a - mean) / std).collect();
    let mb = n / cfg.minibatches;
    let mut stats = UpdateStats::default();
    let mut count = 0.0;
    let mut order: Vec<usize> = (0..n).collect();
    for _ in 0..cfg.epochs {
        order.shuffle(rng);
        for chunk in order.chunks(mb).filter(|c| c.len() == mb) {
            // Row copies, where an element-wise iterator took a tenth of the update.
            let gather = |src: &[f32], w: usize| {
                let mut rows = Vec::with_capacity(chunk.len() * w);
                chunk.iter().for_each(|&k| rows.extend_from_slice(&src[k * w..(k + 1) * w]));
                rows
            };
            let obs = gather(&r.obs, obs_dim);
            let actions = gather(&r.actions, act);
            let old_means = gather(&r.means, act);
            // Actor and critic side by side, one per thread: their products are of equal size,
            // and two whole networks in parallel waste less than splitting each product.
            let (actor_tape, critic_tape) =
                rayon::join(|| policy.actor.forward(&obs, mb), || policy.critic.forward(&obs, mb));
            let loss = minibatch_loss(
                &Minibatch {
                    means: &actor_tape.output,
                    values: &critic_tape.output,
                    actions: &actions,
                    old_log_probs: &gather(&r.log_probs, 1),
                    advantages: &gather(&adv, 1),
                    old_values: &gather(&r.values, 1),
                    returns: &gather(&returns, 1),
                },
                &policy.log_std,
                cfg,
            );
            let MinibatchLoss { surrogate: surr, value_loss: vloss, clipped, g_mean, g_value, g_log_std } = loss;
            let (mut kl, inv) = (0.0, 1.0 / mb as f32);
            let entropy: f32 = policy.log_std.iter().map(|s| s + 1.418_938_5).sum();
            let mut grads = vec![0.0; policy.num_params()];
            let (na, nc) = (policy.actor.num_params(), policy.critic.num_params());
            let (actor_grads, rest) = grads.split_at_mut(na);
            rayon::join(
                || policy.actor.backward(&actor_tape, &g_mean, actor_grads),
                || policy.critic.backward(&critic_tape, &g_value, &mut rest[..nc]),
            );
            grads[na + nc..].copy_from_slice(&g_log_std);
            let norm = grads.iter().map(|g| g * g).sum::<f32>().sqrt();
            if norm > cfg.max_grad_norm as f32 {
                let s = cfg.max_grad_norm as f32 / norm;
                grads.iter_mut().for_each(|g| *g *= s);
            }
            // Adaptive learning rate (rsl_rl): KL from the policy that collected the data to
            // the current one, before this step.
            // Per dimension: s1 - s0 + (var0 + (m0 - m1)^2) / (2 var1) - 1/2.
            let (var0, half_inv_var1): (Vec<f32>, Vec<f32>) = r
                .log_std
                .iter()
                .zip(&policy.log_std)
                .map(|(s0, s1)| ((2.0 * s0).exp(), 0.5 * (-2.0 * s1).exp()))
                .unzip();
            for row in 0..mb {
                for j in 0..act {
                    let (s0, s1) = (r.log_std[j], policy.log_std[j]);
                    let (m0, m1) = (old_means[row * act + j], actor_tape.output[row * act + j]);
                    kl += (s1 - s0 + (var0[j] + (m0 - m1).powi(2)) * half_inv_var1[j] - 0.5) * inv;
                }
            }
            let target = cfg.kl_target as f32;
            if kl > 2.0 * target {
                opt.lr = (opt.lr / 1.5).max(1e-5);
            } else if kl < 0.5 * target && kl > 0.0 {
                opt.lr = (opt.lr * 1.5).min(1e-2);
            }
            let mut p = policy.params();
            opt.adam.step(&mut p, &grads, opt.lr);
            policy.set_params(&p);
            // The exploration noise never grows past its initial value: with small batches the
            // surrogate's pull on the log-std is mostly noise, and every corpus and per-clip run
            // drifted upward (mean log-std -0.5 to +0.08 in 2,850 iterations) while tracking got
            // worse.
            let ceiling = cfg.init_log_std as f32;
            policy.log_std.iter_mut().for_each(|s| *s = s.min(ceiling));
            stats.surrogate += surr;
            stats.value_loss += vloss;
            stats.entropy += entropy;
            stats.kl += kl;
            stats.clip_fraction += clipped;
            count += 1.0;
        }
    }
    for x in [&mut stats.surrogate, &mut stats.value_loss, &mut stats.entropy, &mut stats.kl, &mut stats.clip_fraction]
    {
        *x /= count;
    }
    stats.learning_rate = opt.lr;
    stats
}

#[cfg(test)]
mod tests {
    use super::*;
    use rand::SeedableRng;

    #[test]
    fn the_minibatch_loss_gradients_match_finite_differences() {
        let mut rng = rand::rngs::StdRng::seed_from_u64(5);
        let (mb, act) = (8, 3);
        let mut normal = |n: usize, scale: f32| -> Vec<f32> {
            (0..n)
                .map(|_| {
                    let z: f32 = StandardNormal.sample(&mut rng);
                    scale * z
                })
                .collect()
        };
        let (means, values, actions) = (normal(mb * act, 0.5), normal(mb, 1.0), normal(mb * act, 0.5));
        let log_std = vec![-0.5, -0.3, -0.7];
        let inv_std = inverse_std(&log_std);
        // Old log-probabilities near the current ones: ratios around 1, some beyond the clip.
        let old_log_probs: Vec<f32> = (0..mb)
            .map(|i| {
                log_prob(&actions[i * act..][..act], &means[i * act..][..act], &log_std, &inv_std)
                    + 0.15 * normal(1, 1.0)[0]
            })
            .collect();
        let (advantages, old_values, returns) = (normal(mb, 1.0), normal(mb, 1.0), normal(mb, 1.0));
        let cfg = TrackConfig { entropy: 0.01, value_coef: 0.7, ..TrackConfig::default() };
        let total = |means: &[f32], values: &[f32], log_std: &[f32]| -> f64 {
            let b = Minibatch {
                means,
                values,
                actions: &actions,
                old_log_probs: &old_log_probs,
                advantages: &advantages,
                old_values: &old_values,
                returns: &returns,
            };
            let l = minibatch_loss(&b, log_std, &cfg);
            let entropy: f32 = log_std.iter().map(|s| s + 1.418_938_5).sum();
            f64::from(l.surrogate) + cfg.value_coef * f64::from(l.value_loss) - cfg.entropy * f64::from(entropy)
        };
        let b = Minibatch {
            means: &means,
            values: &values,
            actions: &actions,
            old_log_probs: &old_log_probs,
            advantages: &advantages,
            old_values: &old_values,
            returns: &returns,
        };
        let loss = minibatch_loss(&b, &log_std, &cfg);
        assert!(loss.clipped > 0.0 && loss.clipped < 1.0, "some ratios clipped, some not: {}", loss.clipped);
        // Central differences, where the two one-sided ones agree (away from a clip's kink).
        let eps = 1e-3;
        let mut checked = 0;
        let mut check = |what: &str, analytic: &[f32], at: &dyn Fn(usize, f32) -> f64| {
            for (i, &g) in analytic.iter().enumerate() {
                let (up, here, down) = (at(i, eps), at(i, 0.0), at(i, -eps));
                let (right, left) = ((up - here) / f64::from(eps), (here - down) / f64::from(eps));
                if (right - left).abs() > 0.05 * right.abs().max(left.abs()) + 1e-3 {
                    continue;
                }
                let fd = (up - down) / f64::from(2.0 * eps);
                assert!(
                    (fd - f64::from(g)).abs() < 2e-3 + 0.02 * fd.abs(),
                    "{what}[{i}]: analytic {g}, finite differences {fd}"
                );
                checked += 1;
            }
        };
        let moved = |v: &[f32], i: usize, d: f32| -> Vec<f32> {
            let mut v = v.to_vec();
            v[i] += d;
            v
        };
        check("mean", &loss.g_mean, &|i, d| total(&moved(&means, i, d), &values, &log_std));
        check("value", &loss.g_value, &|i, d| total(&means, &moved(&values, i, d), &log_std));
        check("log_std", &loss.g_log_std, &|i, d| total(&means, &values, &moved(&log_std, i, d)));
        assert!(checked >= 25, "only {checked} entries away from a kink");
    }

    #[test]
    fn gae_matches_hand_computation() {
        // One env, three steps, done after the second.
        let r = RolloutBuffer {
            envs: 1,
            obs: vec![],
            actions: vec![],
            log_probs: vec![],
            means: vec![],
            log_std: vec![],
            values: vec![1.0, 2.0, 3.0],
            rewards: vec![1.0, 1.0, 1.0],
            dones: vec![false, true, false],
            last_values: vec![4.0],
        };
        let (adv, ret) = advantages(&r, 0.9, 0.5);
        let d2 = 1.0 + 0.9 * 4.0 - 3.0;
        let d1 = 1.0 - 2.0; // terminal: no bootstrap
        let d0 = 1.0 + 0.9 * 2.0 - 1.0;
        let expect = [d0 + 0.45 * d1, d1, d2];
        for k in 0..3 {
            assert!((adv[k] - expect[k]).abs() < 1e-6, "{k}: {} vs {}", adv[k], expect[k]);
            assert!((ret[k] - (expect[k] + r.values[k])).abs() < 1e-6);
        }
    }

    #[test]
    fn log_std_stays_at_or_below_its_initial_value() {
        // A large entropy bonus pushes every log-std up; the ceiling holds it at init_log_std.
        let cfg = TrackConfig { hidden: vec![8], entropy: 10.0, learning_rate: 1e-2, ..Default::default() };
        let mut rng = rand::rngs::StdRng::seed_from_u64(1);
        let mut policy = Policy::new(3, 2, &cfg, &mut rng);
        let mut opt = Optimiser { adam: Adam::new(policy.num_params()), lr: 1e-2 };
        let n = 64;
        let obs: Vec<f32> = (0..n * 3).map(|i| (i % 7) as f32 * 0.1).collect();
        let s = sample(&policy, &obs, n, &mut rng);
        let r = RolloutBuffer {
            envs: n,
            obs,
            actions: s.actions,
            log_probs: s.log_probs,
            means: s.means,
            log_std: policy.log_std.clone(),
            values: s.values,
            rewards: (0..n).map(|i| (i % 3) as f32).collect(),
            dones: vec![false; n],
            last_values: vec![0.0; n],
        };
        let before = policy.params();
        update(&mut policy, &mut opt, &r, &cfg, &mut rng);
        assert_ne!(before, policy.params(), "the update changed nothing");
        assert!(policy.log_std.iter().all(|&s| s <= cfg.init_log_std as f32), "{:?}", policy.log_std);
    }

    #[test]
    fn normaliser_tracks_mean_and_variance() {
        let mut n = Normaliser::new(2);
        let rows: Vec<f32> = (0..1000).flat_map(|i| [i as f32, 5.0]).collect();
        // Two batches of 400 and 600 rows merge into the statistics of all 1000.
        n.update(&rows[..800]);
        n.update(&rows[800..]);
        assert!((n.mean[0] - 499.5).abs() < 0.01 && (n.mean[1] - 5.0).abs() < 1e-3, "{:?}", n.mean);
        let var: f64 = (0..1000).map(|i| (i as f64 - 499.5).powi(2)).sum::<f64>() / 1000.0;
        assert!((n.var[0] - var).abs() / var < 1e-3, "{} vs {var}", n.var[0]);
    }
}

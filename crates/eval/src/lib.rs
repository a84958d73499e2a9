//! The paper's evaluation: metrics as plain functions of recorded rollouts (so they can be
//! checked on hand-made traces), the [`protocols`] that produce those rollouts, and the
//! [`sweep`] that runs a protocol over models and sampler points, stores every trial and writes
//! the report, and the paper's [`experiments`] built from them.

pub mod experiments;
pub mod outcome;
pub mod protocols;
pub mod sweep;

/// Mean and (population) standard deviation.
pub fn mean_std(values: &[f64]) -> (f64, f64) {
    if values.is_empty() {
        return (f64::NAN, f64::NAN);
    }
    let n = values.len() as f64;
    let mean = values.iter().sum::<f64>() / n;
    (mean, (values.iter().map(|v| (v - mean).powi(2)).sum::<f64>() / n).sqrt())
}

/// Survival protocol: control steps survived in one trial, given the step at which the head
/// first went below 0.2 m (`None`: never) and the episode cap.
pub fn survival_steps(fall_step: Option<usize>, cap: usize) -> usize {
    fall_step.map_or(cap, |s| s.min(cap))
}

/// Root-mean-square error between commanded and achieved planar velocities, m/s.
pub fn velocity_rmse(commanded: &[[f64; 2]], achieved: &[[f64; 2]]) -> f64 {
    assert_eq!(commanded.len(), achieved.len(), "one achieved velocity per command");
    if commanded.is_empty() {
        return f64::NAN;
    }
    let sum: f64 = commanded.iter().zip(achieved).map(|(c, a)| (c[0] - a[0]).powi(2) + (c[1] - a[1]).powi(2)).sum();
    (sum / commanded.len() as f64).sqrt()
}

/// Mean and root-mean-square hand-to-target distance over a trial, m.
pub fn reach_errors(hand: &[[f64; 3]], target: &[[f64; 3]]) -> (f64, f64) {
    assert_eq!(hand.len(), target.len(), "one target per hand sample");
    let d: Vec<f64> = hand
        .iter()
        .zip(target)
        .map(|(h, t)| ((h[0] - t[0]).powi(2) + (h[1] - t[1]).powi(2) + (h[2] - t[2]).powi(2)).sqrt())
        .collect();
    let n = d.len().max(1) as f64;
    (d.iter().sum::<f64>() / n, (d.iter().map(|x| x * x).sum::<f64>() / n).sqrt())
}

/// How close (m) the hand must come to its target to count as there: composition success and
/// the reach protocol's "within 0.15 m".
pub const HAND_REACHED: f64 = 0.15;

/// Composition success: pelvis within 0.5 m of the waypoint and hand within [`HAND_REACHED`] of
/// the target at the same time.
pub fn composition_success(pelvis_to_waypoint: f64, hand_to_target: f64) -> bool {
    pelvis_to_waypoint <= 0.5 && hand_to_target <= HAND_REACHED
}

/// Mean vector and covariance matrix (row-major) of feature rows.
pub fn gaussian(features: &[Vec<f64>]) -> (Vec<f64>, Vec<f64>) {
    let n = features.len() as f64;
    let d = features.first().map_or(0, Vec::len);
    let mut mean = vec![0.0; d];
    for f in features {
        mean.iter_mut().zip(f).for_each(|(m, x)| *m += x / n);
    }
    let mut cov = vec![0.0; d * d];
    for f in features {
        for i in 0..d {
            for j in 0..d {
                cov[i * d + j] += (f[i] - mean[i]) * (f[j] - mean[j]) / n;
            }
        }
    }
    (mean, cov)
}

/// Eigenvalues and eigenvectors (columns) of a symmetric matrix by cyclic Jacobi rotations.
fn symmetric_eigen(a: &[f64], d: usize) -> (Vec<f64>, Vec<f64>) {
    let mut a = a.to_vec();
    let mut v: Vec<f64> = (0..d * d).map(|k| if k / d == k % d { 1.0 } else { 0.0 }).collect();
    for _sweep in 0..100 {
        let off: f64 = (0..d)
            .flat_map(|i| (0..d).filter(move |&j| j != i).map(move |j| (i, j)))
            .map(|(i, j)| a[i * d + j].powi(2))
            .sum();
        if off < 1e-22 {
            break;
        }
        for p in 0..d {
            for q in p + 1..d {
                let apq = a[p * d + q];
                if apq.abs() < 1e-300 {
                    continue;
                }
                let theta = (a[q * d + q] - a[p * d + p]) / (2.0 * apq);
                let t = theta.signum() / (theta.abs() + (theta * theta + 1.0).sqrt());
                let t = if theta == 0.0 { 1.0 } else { t };
                let (c, s) = (1.0 / (t * t + 1.0).sqrt(), t / (t * t + 1.0).sqrt());
                for k in 0..d {
                    let (akp, akq) = (a[k * d + p], a[k * d + q]);
                    a[k * d + p] = c * akp - s * akq;
                    a[k * d + q] = s * akp + c * akq;
                }
                for k in 0..d {
                    let (apk, aqk) = (a[p * d + k], a[q * d + k]);
                    a[p * d + k] = c * apk - s * aqk;
                    a[q * d + k] = s * apk + c * aqk;
                }
                for k in 0..d {
                    let (vkp, vkq) = (v[k * d + p], v[k * d + q]);
                    v[k * d + p] = c * vkp - s * vkq;
                    v[k * d + q] = s * vkp + c * vkq;
                }
            }
        }
    }
    ((0..d).map(|i| a[i * d + i]).collect(), v)
}

/// The symmetric positive semi-definite square root (negative eigenvalues from rounding are
/// clamped to zero).
fn sqrt_psd(a: &[f64], d: usize) -> Vec<f64> {
    let (w, v) = symmetric_eigen(a, d);
    let mut out = vec![0.0; d * d];
    for i in 0..d {
        for j in 0..d {
            out[i * d + j] = (0..d).map(|k| v[i * d + k] * w[k].max(0.0).sqrt() * v[j * d + k]).sum();
        }
    }
    out
}

fn matmul(a: &[f64], b: &[f64], d: usize) -> Vec<f64> {
    let mut out = vec![0.0; d * d];
    for i in 0..d {
        for k in 0..d {
            let aik = a[i * d + k];
            for j in 0..d {
                out[i * d + j] += aik * b[k * d + j];
            }
        }
    }
    out
}

/// Fréchet distance between Gaussians N(m1, S1) and N(m2, S2):
/// `||m1 - m2||^2 + Tr(S1 + S2 - 2 (S1^{1/2} S2 S1^{1/2})^{1/2})` (the FID formula on motion
/// features).
pub fn frechet_distance(m1: &[f64], s1: &[f64], m2: &[f64], s2: &[f64]) -> f64 {
    let d = m1.len();
    let mean: f64 = m1.iter().zip(m2).map(|(a, b)| (a - b).powi(2)).sum();
    let r1 = sqrt_psd(s1, d);
    let inner = matmul(&matmul(&r1, s2, d), &r1, d);
    // Symmetrise against rounding before the eigen-decomposition.
    let sym: Vec<f64> = (0..d * d).map(|k| 0.5 * (inner[k] + inner[(k % d) * d + k / d])).collect();
    let (w, _) = symmetric_eigen(&sym, d);
    let cross: f64 = w.iter().map(|x| x.max(0.0).sqrt()).sum();
    let trace = |s: &[f64]| (0..d).map(|i| s[i * d + i]).sum::<f64>();
    (mean + trace(s1) + trace(s2) - 2.0 * cross).max(0.0)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn survival_counts_steps_to_the_fall_or_the_cap() {
        assert_eq!(survival_steps(Some(137), 1000), 137);
        assert_eq!(survival_steps(None, 1000), 1000);
        assert_eq!(survival_steps(Some(5000), 1000), 1000);
        let (m, s) = mean_std(&[100.0, 300.0]);
        assert_eq!((m, s), (200.0, 100.0));
    }

    #[test]
    fn a_known_velocity_trace_gives_a_known_rmse() {
        // Commanded 1 m/s forward; achieved 0.8 half the time and 1.2 the other half: RMSE 0.2.
        let cmd = vec![[1.0, 0.0]; 4];
        let got = [[0.8, 0.0], [1.2, 0.0], [0.8, 0.0], [1.2, 0.0]];
        assert!((velocity_rmse(&cmd, &got) - 0.2).abs() < 1e-12);
        // Sideways error counts too: 3-4-5.
        assert!((velocity_rmse(&[[0.0, 0.0]], &[[0.3, 0.4]]) - 0.5).abs() < 1e-12);
    }

    #[test]
    fn reach_and_composition() {
        let (mean, rms) = reach_errors(&[[0.0, 0.0, 1.0], [0.0, 0.0, 1.0]], &[[0.3, 0.4, 1.0], [0.0, 0.0, 1.0]]);
        assert!((mean - 0.25).abs() < 1e-12 && (rms - (0.125f64).sqrt()).abs() < 1e-12);
        assert!(composition_success(0.4, 0.1) && !composition_success(0.6, 0.1) && !composition_success(0.4, 0.2));
    }

    #[test]
    fn frechet_distance_matches_closed_forms() {
        let d = 3;
        let s: Vec<f64> = vec![2.0, 0.3, 0.1, 0.3, 1.0, -0.2, 0.1, -0.2, 0.5];
        let m = vec![0.1, -0.2, 0.3];
        assert!(frechet_distance(&m, &s, &m, &s).abs() < 1e-9, "identical Gaussians");
        let shifted: Vec<f64> = m.iter().map(|x| x + 1.0).collect();
        assert!((frechet_distance(&m, &s, &shifted, &s) - 3.0).abs() < 1e-9, "a mean shift adds its square");
        // Commuting covariances: sum over eigen-directions of (sqrt(a) - sqrt(b))^2.
        let a: Vec<f64> = (0..d * d).map(|k| if k / d == k % d { [4.0, 1.0, 9.0][k / d] } else { 0.0 }).collect();
        let b: Vec<f64> = (0..d * d).map(|k| if k / d == k % d { [1.0, 1.0, 4.0][k / d] } else { 0.0 }).collect();
        assert!((frechet_distance(&m, &a, &m, &b) - (1.0 + 0.0 + 1.0)).abs() < 1e-9);
        // Sample statistics.
        let rows: Vec<Vec<f64>> = (0..4).map(|i| vec![i as f64, 2.0 * i as f64]).collect();
        let (mean, cov) = gaussian(&rows);
        assert_eq!(mean, vec![1.5, 3.0]);
        assert!((cov[0] - 1.25).abs() < 1e-12 && (cov[1] - 2.5).abs() < 1e-12 && (cov[3] - 5.0).abs() < 1e-12);
    }

    #[test]
    fn jacobi_reconstructs_the_matrix() {
        let d = 4;
        let a: Vec<f64> = (0..d * d)
            .map(|k| {
                let (i, j) = (k / d, k % d);
                1.0 / (1.0 + i as f64 + j as f64) + if i == j { 1.0 } else { 0.0 }
            })
            .collect();
        let r = sqrt_psd(&a, d);
        let back = matmul(&r, &r, d);
        for k in 0..d * d {
            assert!((back[k] - a[k]).abs() < 1e-9, "sqrt(A)^2 = A at {k}");
        }
    }
}

//! Mirror-symmetric sampling: the network averaged with its own mirror image,
//! `f_sym(x, c) = (f(x, c) + M f(M x, M c)) / 2`, both halves in one batched call. Walking data
//! turns both ways, and the simulated humanoid is mirror-symmetric to within 0.001 over 2 s
//! (`flowmimic_sim::Mirror`), but a trained network is not: the shipped models circle left when
//! left alone, even one trained on a dataset with every clip's mirror image. A flow whose
//! velocity field is mirror-symmetric, started from mirror-symmetric noise, samples a
//! mirror-symmetric distribution of trajectories.
//!
//! The mirror acts on the normalised coordinates, where it is exact when the normalisation
//! statistics are themselves mirror-symmetric (a mirrored dataset's are) and otherwise off by
//! the left-right difference of the statistics.

use crate::Network;
use flowmimic_sim::Mirror;

/// A network and the mirror of its conditioning and of its samples.
pub(crate) struct Mirrored<'a> {
    pub net: &'a dyn Network,
    pub cond: &'a Mirror,
    pub sample: &'a Mirror,
}

impl Mirrored<'_> {
    /// The batch of `n` rows followed by their mirror images.
    fn doubled(&self, x: &[f32], t: &[f32], cond: &[f32], n: usize) -> (Vec<f32>, Vec<f32>, Vec<f32>) {
        let with_image = |x: &[f32], mirror: &Mirror| {
            let mut both = x.to_vec();
            let mut image = x.to_vec();
            mirror.apply_rows(&mut image);
            both.extend(image);
            both
        };
        // Each row's noise levels (one or two blocks of n) repeat for its image.
        let t = t.chunks(n.max(1)).flat_map(|block| block.iter().chain(block)).copied().collect();
        (with_image(x, self.sample), t, with_image(cond, self.cond))
    }

    /// `(a + M b) / 2` for the first and second halves `a`, `b` of `both`.
    fn average(&self, both: &[f32]) -> Vec<f32> {
        let (a, b) = both.split_at(both.len() / 2);
        let mut image = b.to_vec();
        self.sample.apply_rows(&mut image);
        a.iter().zip(image).map(|(a, b)| 0.5 * (a + b)).collect()
    }
}

impl Network for Mirrored<'_> {
    fn dim(&self) -> usize {
        self.net.dim()
    }

    fn predict(&self, x: &[f32], t: &[f32], cond: &[f32], n: usize) -> Vec<f32> {
        let (x, t, cond) = self.doubled(x, t, cond, n);
        self.average(&self.net.predict(&x, &t, &cond, 2 * n))
    }

    /// The cotangent `u` of the average reaches the halves as `u / 2` and `M u / 2` (the mirror
    /// is its own transpose), and their gradients come back the same way: `g_a + M g_b`.
    fn predict_pullback(
        &self,
        x: &[f32],
        t: &[f32],
        cond: &[f32],
        n: usize,
        cotangent: &mut dyn FnMut(&[f32]) -> Vec<f32>,
    ) -> (Vec<f32>, Vec<f32>) {
        let (x, t, cond) = self.doubled(x, t, cond, n);
        let mut y = Vec::new();
        let (_, pulled) = self.net.predict_pullback(&x, &t, &cond, 2 * n, &mut |both| {
            y = self.average(both);
            let half: Vec<f32> = cotangent(&y).iter().map(|u| 0.5 * u).collect();
            let mut image = half.clone();
            self.sample.apply_rows(&mut image);
            half.into_iter().chain(image).collect()
        });
        (y, self.average(&pulled).into_iter().map(|g| 2.0 * g).collect())
    }
}

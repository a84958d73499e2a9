//! Direct kernels for the products of a dense layer's forward pass and its input gradient. SGEMM
//! packs both operands on every call; with one sample's 13-21 rows the packing of the weights
//! cost a quarter of the guided control step (perf, README "Benchmarks"), so these read the
//! weights where they lie. Larger batches are split into blocks of rows over rayon's threads by
//! the caller. They need AVX2 and FMA; elsewhere the callers keep SGEMM.

/// Rows that share each weight chunk loaded.
const ROWS: usize = 4;

/// Whether this CPU runs the kernels.
pub(crate) fn available() -> bool {
    #[cfg(target_arch = "x86_64")]
    {
        std::is_x86_feature_detected!("avx2") && std::is_x86_feature_detected!("fma")
    }
    #[cfg(not(target_arch = "x86_64"))]
    {
        false
    }
}

/// Rows from which SGEMM beats these kernels on a CPU with AVX-512, where `matrixmultiply` runs
/// 16-lane kernels against these 8: a PPO minibatch of 1,408 rows through the 295-256-128-64
/// networks took 6.9-7.3 ms against 8.6-8.9 forward, and a training step of the cpu preset's
/// Transformer (5,376 rows) 266-274 ms against 280-292 with the input gradient on SGEMM too
/// (docs/benchmarks.md).
const SGEMM_ROWS_AVX512: usize = 1024;

/// Whether a product of `rows` rows (forward or input gradient) is faster on SGEMM than on
/// these kernels.
pub(crate) fn sgemm_is_faster(rows: usize) -> bool {
    #[cfg(target_arch = "x86_64")]
    {
        rows >= SGEMM_ROWS_AVX512 && std::is_x86_feature_detected!("avx512f")
    }
    #[cfg(not(target_arch = "x86_64"))]
    {
        let _ = rows;
        false
    }
}

/// `y[r][o] = x[r][..] . w[o][..] + b[o]` into `y` (rows x outputs); `x` is rows x inputs, `w`
/// outputs x inputs.
pub(crate) fn forward(x: &[f32], rows: usize, w: &[f32], b: &[f32], inputs: usize, y: &mut [f32]) {
    assert!(available(), "the direct kernels need AVX2 and FMA");
    assert!(
        x.len() >= rows * inputs && w.len() == b.len() * inputs && y.len() >= rows * b.len(),
        "forward operands do not match"
    );
    #[cfg(target_arch = "x86_64")]
    // SAFETY: the CPU has AVX2 and FMA, and the operands' sizes were checked above.
    unsafe {
        avx2::forward(x, rows, w, b, inputs, y)
    };
}

/// `dx[r][i] = sum_o dy[r][o] w[o][i]` into `dx` (rows x inputs): the gradient of a dense
/// layer with respect to its input.
pub(crate) fn input_grad(dy: &[f32], rows: usize, w: &[f32], inputs: usize, dx: &mut [f32]) {
    assert!(available(), "the direct kernels need AVX2 and FMA");
    let outputs = w.len() / inputs;
    assert!(
        dy.len() >= rows * outputs && w.len() == outputs * inputs && dx.len() >= rows * inputs,
        "input-gradient operands do not match"
    );
    #[cfg(target_arch = "x86_64")]
    // SAFETY: the CPU has AVX2 and FMA, and the operands' sizes were checked above.
    unsafe {
        avx2::input_grad(dy, rows, w, inputs, dx)
    };
}

/// The kernels on AVX2 registers. Their callers check the operands' sizes; inside, the loads
/// and stores use raw pointers at offsets those sizes bound.
#[cfg(target_arch = "x86_64")]
mod avx2 {
    use std::arch::x86_64::*;

    use super::ROWS;

    /// f32 lanes of one register.
    const LANES: usize = 8;

    #[target_feature(enable = "avx2,fma")]
    pub(super) unsafe fn forward(x: &[f32], rows: usize, w: &[f32], b: &[f32], inputs: usize, y: &mut [f32]) {
        let outputs = b.len();
        let mut r = 0;
        while r < rows {
            let tile = if rows - r >= ROWS { ROWS } else { 1 };
            let mut o = 0;
            while o < outputs {
                let step = (outputs - o).min(3);
                // SAFETY: rows r .. r + tile of x and y and outputs o .. o + step of w exist.
                unsafe {
                    match (tile, step) {
                        (ROWS, 3) => dot_tile::<ROWS, 3>(x, r, w, o, (b, inputs), y),
                        (ROWS, 2) => dot_tile::<ROWS, 2>(x, r, w, o, (b, inputs), y),
                        (ROWS, _) => dot_tile::<ROWS, 1>(x, r, w, o, (b, inputs), y),
                        (_, 3) => dot_tile::<1, 3>(x, r, w, o, (b, inputs), y),
                        (_, 2) => dot_tile::<1, 2>(x, r, w, o, (b, inputs), y),
                        (_, _) => dot_tile::<1, 1>(x, r, w, o, (b, inputs), y),
                    }
                }
                o += step;
            }
            r += tile;
        }
    }

    /// `y[r + i][o + j]` for R rows and O outputs: R x O dot products of length `inputs` in
    /// R x O registers, each summed across its lanes at the end.
    #[target_feature(enable = "avx2,fma")]
    #[inline]
    unsafe fn dot_tile<const R: usize, const O: usize>(
        x: &[f32],
        r: usize,
        w: &[f32],
        o: usize,
        (b, k): (&[f32], usize),
        y: &mut [f32],
    ) {
        // SAFETY: the caller passes rows r .. r + R of x and y and outputs o .. o + O of w, each
        // row `k` long.
        unsafe {
            let outputs = b.len();
            let (x, w) = (x.as_ptr().add(r * k), w.as_ptr().add(o * k));
            let mut acc = [[_mm256_setzero_ps(); O]; R];
            let full = k / LANES * LANES;
            let mut c = 0;
            while c < full {
                let mut wv = [_mm256_setzero_ps(); O];
                for (j, wv) in wv.iter_mut().enumerate() {
                    *wv = _mm256_loadu_ps(w.add(j * k + c));
                }
                for (i, acc) in acc.iter_mut().enumerate() {
                    let xv = _mm256_loadu_ps(x.add(i * k + c));
                    for (acc, wv) in acc.iter_mut().zip(&wv) {
                        *acc = _mm256_fmadd_ps(xv, *wv, *acc);
                    }
                }
                c += LANES;
            }
            // The last k - full (< 8) columns by masked loads, which read nothing past them: one
            // more step where a scalar loop cost a fifth of a 295-wide layer.
            if full < k {
                let lanes = _mm256_setr_epi32(0, 1, 2, 3, 4, 5, 6, 7);
                let mask = _mm256_cmpgt_epi32(_mm256_set1_epi32((k - full) as i32), lanes);
                let mut wv = [_mm256_setzero_ps(); O];
                for (j, wv) in wv.iter_mut().enumerate() {
                    *wv = _mm256_maskload_ps(w.add(j * k + full), mask);
                }
                for (i, acc) in acc.iter_mut().enumerate() {
                    let xv = _mm256_maskload_ps(x.add(i * k + full), mask);
                    for (acc, wv) in acc.iter_mut().zip(&wv) {
                        *acc = _mm256_fmadd_ps(xv, *wv, *acc);
                    }
                }
            }
            for (i, acc) in acc.iter().enumerate() {
                for (j, acc) in acc.iter().enumerate() {
                    y[(r + i) * outputs + o + j] = lane_sum(*acc) + b[o + j];
                }
            }
        }
    }

    #[target_feature(enable = "avx2,fma")]
    #[inline]
    fn lane_sum(v: __m256) -> f32 {
        let s = _mm_add_ps(_mm256_castps256_ps128(v), _mm256_extractf128_ps(v, 1));
        let s = _mm_add_ps(s, _mm_movehl_ps(s, s));
        _mm_cvtss_f32(_mm_add_ss(s, _mm_shuffle_ps(s, s, 1)))
    }

    #[target_feature(enable = "avx2,fma")]
    pub(super) unsafe fn input_grad(dy: &[f32], rows: usize, w: &[f32], inputs: usize, dx: &mut [f32]) {
        let mut r = 0;
        while r < rows {
            let tile = if rows - r >= ROWS { ROWS } else { 1 };
            // SAFETY: rows r .. r + tile of dy and dx exist.
            unsafe {
                if tile == ROWS {
                    axpy_rows::<ROWS>(dy, r, w, inputs, dx);
                } else {
                    axpy_rows::<1>(dy, r, w, inputs, dx);
                }
            }
            r += tile;
        }
    }

    /// Rows `r .. r + R` of `dx = dy w`: two registers of columns at a time, accumulating
    /// `dy[r][o] w[o][..]` over the outputs; the last columns (fewer than two registers) one
    /// by one.
    #[target_feature(enable = "avx2,fma")]
    #[inline]
    unsafe fn axpy_rows<const R: usize>(dy: &[f32], r: usize, w: &[f32], inputs: usize, dx: &mut [f32]) {
        // SAFETY: the caller passes rows r .. r + R of dy and dx; every column read is below
        // `inputs`.
        unsafe {
            let outputs = w.len() / inputs;
            let (dy, wp, out) = (dy.as_ptr().add(r * outputs), w.as_ptr(), dx.as_mut_ptr().add(r * inputs));
            let full = inputs / (2 * LANES) * (2 * LANES);
            let mut c = 0;
            while c < full {
                let mut acc = [[_mm256_setzero_ps(); 2]; R];
                for o in 0..outputs {
                    let wv = [_mm256_loadu_ps(wp.add(o * inputs + c)), _mm256_loadu_ps(wp.add(o * inputs + c + LANES))];
                    for (i, acc) in acc.iter_mut().enumerate() {
                        let s = _mm256_broadcast_ss(&*dy.add(i * outputs + o));
                        acc[0] = _mm256_fmadd_ps(s, wv[0], acc[0]);
                        acc[1] = _mm256_fmadd_ps(s, wv[1], acc[1]);
                    }
                }
                for (i, acc) in acc.iter().enumerate() {
                    _mm256_storeu_ps(out.add(i * inputs + c), acc[0]);
                    _mm256_storeu_ps(out.add(i * inputs + c + LANES), acc[1]);
                }
                c += 2 * LANES;
            }
            if full < inputs {
                for i in 0..R {
                    let row = &mut dx[(r + i) * inputs + full..(r + i + 1) * inputs];
                    for o in 0..outputs {
                        let s = *dy.add(i * outputs + o);
                        let wrow = &w[o * inputs + full..(o + 1) * inputs];
                        row.iter_mut().zip(wrow).for_each(|(d, w)| *d += s * w);
                    }
                }
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn values(len: usize, seed: usize) -> Vec<f32> {
        (0..len).map(|i| ((i * 37 + seed * 11) % 101) as f32 / 50.0 - 1.0).collect()
    }

    #[test]
    fn the_direct_kernels_equal_sgemm_on_every_tile_and_tail() {
        if !available() {
            return;
        }
        for (rows, inputs, outputs) in
            [(1, 1, 1), (3, 7, 5), (4, 16, 2), (5, 17, 3), (9, 40, 33), (21, 128, 384), (21, 512, 128)]
        {
            let (x, w, b) = (values(rows * inputs, 1), values(outputs * inputs, 2), values(outputs, 3));
            let mut y = b.repeat(rows);
            crate::dense::gemm(rows, inputs, outputs, (&x, inputs as isize, 1), (&w, 1, inputs as isize), &mut y, 1.0);
            let close = |a: &[f32], b: &[f32]| a.iter().zip(b).all(|(a, b)| (a - b).abs() <= 1e-5 * (1.0 + b.abs()));
            let mut direct = vec![0.0; rows * outputs];
            forward(&x, rows, &w, &b, inputs, &mut direct);
            assert!(close(&direct, &y), "forward {rows} x {inputs} -> {outputs}");
            let dy = values(rows * outputs, 4);
            let mut dx = vec![0.0; rows * inputs];
            crate::dense::gemm(
                rows,
                outputs,
                inputs,
                (&dy, outputs as isize, 1),
                (&w, inputs as isize, 1),
                &mut dx,
                0.0,
            );
            let mut direct = vec![0.0; rows * inputs];
            input_grad(&dy, rows, &w, inputs, &mut direct);
            assert!(close(&direct, &dx), "input gradient {rows} x {outputs} -> {inputs}");
        }
    }
}

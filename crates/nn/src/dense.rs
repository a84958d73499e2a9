//! Dense layers, row-major: the forward product and its backward, shared by the MLP and the
//! Transformer. The forward product and the input gradient run on the direct kernels of
//! `small` where the CPU has them (on AVX-512, for all but many-row products), the weight
//! gradient (a sum over rows) on `matrixmultiply`'s SGEMM.

use rayon::prelude::*;

use crate::small;

/// Multiply-adds above which a product is split by rows over rayon's threads. Below it one
/// thread is faster: `matrixmultiply`'s own threading (which splits small products too, on
/// threads of its own beside rayon's) and a split of the columns both made the batch-1 guided
/// control step slower on 2 cores (README, Benchmarks).
const PARALLEL_WORK: usize = 1 << 21;

/// `c = a b + beta c` for an m x k matrix `a` and a k x n matrix `b` given as (slice, row
/// stride, column stride); `c` is m x n row-major. Large products are split into blocks of rows
/// of `a` and `c`, one per thread.
pub(crate) fn gemm(
    m: usize,
    k: usize,
    n: usize,
    a: (&[f32], isize, isize),
    b: (&[f32], isize, isize),
    c: &mut [f32],
    beta: f32,
) {
    assert!(c.len() >= m * n, "output too small for {m} x {n}");
    assert!(a.1 >= 0 && a.2 >= 0 && b.1 >= 0 && b.2 >= 0, "negative strides");
    by_rows((a.0, a.1 as usize), (c, n), m, m * k * n, |a_rows, rows, c| {
        serial_gemm(rows, k, n, (a_rows, a.1, a.2), b, c, beta)
    });
}

fn serial_gemm(
    m: usize,
    k: usize,
    n: usize,
    a: (&[f32], isize, isize),
    b: (&[f32], isize, isize),
    c: &mut [f32],
    beta: f32,
) {
    let reach = |(s, rs, cs): (&[f32], isize, isize), rows: usize, cols: usize| {
        rows == 0 || cols == 0 || (rows as isize - 1) * rs + (cols as isize - 1) * cs < s.len() as isize
    };
    assert!(reach(a, m, k) && reach(b, k, n), "gemm operand out of bounds");
    // SAFETY: the asserts above keep every strided element inside its slice.
    unsafe {
        matrixmultiply::sgemm(
            m,
            k,
            n,
            1.0,
            a.0.as_ptr(),
            a.1,
            a.2,
            b.0.as_ptr(),
            b.1,
            b.2,
            beta,
            c.as_mut_ptr(),
            n as isize,
            1,
        );
    }
}

/// `y[r][o] = x[r][..] . w[o][..] + b[o]` for `rows` rows; `w` is `[outputs][inputs]`.
pub(crate) fn forward(x: &[f32], rows: usize, w: &[f32], b: &[f32], inputs: usize) -> Vec<f32> {
    let outputs = b.len();
    debug_assert_eq!(w.len(), inputs * outputs);
    if small::available() && !small::sgemm_is_faster(rows) {
        let mut y = vec![0.0; rows * outputs];
        let work = rows * inputs * outputs;
        by_rows((x, inputs), (&mut y, outputs), rows, work, |x, n, y| small::forward(x, n, w, b, inputs, y));
        return y;
    }
    let mut y = b.repeat(rows);
    gemm(rows, inputs, outputs, (x, inputs as isize, 1), (w, 1, inputs as isize), &mut y, 1.0);
    y
}

/// Runs a row-by-row `kernel(a_rows, rows, c_rows)` over `rows` rows of `a` (one every
/// `a_stride` elements) and `c` (`c_width` wide): in one call, or split into one block of rows
/// per rayon thread when the product's `work` (multiply-adds) pays for the split. Each row's
/// result is the same either way.
fn by_rows(
    (a, a_stride): (&[f32], usize),
    (c, c_width): (&mut [f32], usize),
    rows: usize,
    work: usize,
    kernel: impl Fn(&[f32], usize, &mut [f32]) + Sync,
) {
    let threads = rayon::current_num_threads();
    if threads == 1 || rows < 8 * threads || work < PARALLEL_WORK {
        return kernel(a, rows, c);
    }
    let block = rows.div_ceil(threads);
    c[..rows * c_width].par_chunks_mut(block * c_width).enumerate().for_each(|(i, c)| {
        kernel(&a[i * block * a_stride..], c.len() / c_width, c);
    });
}

/// Accumulates `dW += dY^T X`, `db += sum_r dY` and returns `dX = dY W` when asked.
pub(crate) fn backward(
    x: &[f32],
    dy: &[f32],
    rows: usize,
    w: &[f32],
    inputs: usize,
    (gw, gb): (&mut [f32], &mut [f32]),
    want_dx: bool,
) -> Option<Vec<f32>> {
    let outputs = gb.len();
    gemm(outputs, rows, inputs, (dy, 1, outputs as isize), (x, inputs as isize, 1), gw, 1.0);
    for row in dy.chunks_exact(outputs) {
        gb.iter_mut().zip(row).for_each(|(b, g)| *b += g);
    }
    want_dx.then(|| input_grad(dy, rows, w, inputs))
}

/// `dX = dY W`: the gradient with respect to the layer's input alone.
pub(crate) fn input_grad(dy: &[f32], rows: usize, w: &[f32], inputs: usize) -> Vec<f32> {
    let outputs = w.len() / inputs;
    let mut dx = vec![0.0; rows * inputs];
    if small::available() && !small::sgemm_is_faster(rows) {
        let work = rows * inputs * outputs;
        by_rows((dy, outputs), (&mut dx, inputs), rows, work, |dy, n, dx| small::input_grad(dy, n, w, inputs, dx));
    } else {
        gemm(rows, outputs, inputs, (dy, outputs as isize, 1), (w, inputs as isize, 1), &mut dx, 0.0);
    }
    dx
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_product_split_over_threads_equals_the_serial_one() {
        let (m, k, n) = (200, 128, 96);
        let a: Vec<f32> = (0..m * k).map(|i| ((i * 37) % 101) as f32 / 50.0 - 1.0).collect();
        let b: Vec<f32> = (0..m.max(k) * n).map(|i| ((i * 53) % 89) as f32 / 44.0 - 1.0).collect();
        assert!(m * k * n >= PARALLEL_WORK, "large enough to split");
        let pool = rayon::ThreadPoolBuilder::new().num_threads(3).build().unwrap();
        // As stored (row-major a) and transposed (a read down its columns, as a weight
        // gradient reads dY), accumulating into a non-zero c.
        for (a_strides, rows) in [((k as isize, 1), m), ((1, k as isize), k)] {
            let inner = if rows == m { k } else { m };
            let c0: Vec<f32> = (0..rows * n).map(|i| i as f32 * 1e-3).collect();
            let (mut serial, mut split) = (c0.clone(), c0);
            serial_gemm(
                rows,
                inner,
                n,
                (&a, a_strides.0, a_strides.1),
                (&b[..inner * n], n as isize, 1),
                &mut serial,
                1.0,
            );
            pool.install(|| {
                gemm(rows, inner, n, (&a, a_strides.0, a_strides.1), (&b[..inner * n], n as isize, 1), &mut split, 1.0)
            });
            assert_eq!(serial, split);
        }
    }

    #[test]
    fn a_product_is_the_same_on_either_side_of_the_sgemm_threshold() {
        // Wherever SGEMM takes the many-row products (AVX-512), forward and input gradient, it
        // must agree with the direct kernels that take them elsewhere.
        if !small::available() {
            return;
        }
        let (rows, inputs, outputs) = (1100, 37, 19);
        let value = |i: usize| ((i * 31) % 103) as f32 / 51.0 - 1.0;
        let (x, w, b): (Vec<f32>, Vec<f32>, Vec<f32>) = (
            (0..rows * inputs).map(value).collect(),
            (0..outputs * inputs).map(|i| value(i + 5)).collect(),
            (0..outputs).map(value).collect(),
        );
        let mut direct = vec![0.0; rows * outputs];
        small::forward(&x, rows, &w, &b, inputs, &mut direct);
        let close = |a: &[f32], b: &[f32]| a.iter().zip(b).all(|(a, b)| (a - b).abs() <= 1e-5 * (1.0 + b.abs()));
        assert!(close(&forward(&x, rows, &w, &b, inputs), &direct));
        let dy: Vec<f32> = (0..rows * outputs).map(|i| value(i + 2)).collect();
        let mut direct = vec![0.0; rows * inputs];
        small::input_grad(&dy, rows, &w, inputs, &mut direct);
        assert!(close(&input_grad(&dy, rows, &w, inputs), &direct));
    }

    #[test]
    fn dense_layers_split_over_threads_equal_one_thread() {
        let (rows, inputs, outputs) = (300, 96, 80);
        let value = |i: usize| ((i * 29) % 97) as f32 / 48.0 - 1.0;
        let x: Vec<f32> = (0..rows * inputs).map(value).collect();
        let w: Vec<f32> = (0..outputs * inputs).map(|i| value(i + 7)).collect();
        let b: Vec<f32> = (0..outputs).map(value).collect();
        let dy: Vec<f32> = (0..rows * outputs).map(|i| value(i + 3)).collect();
        assert!(rows * inputs * outputs >= PARALLEL_WORK, "large enough to split");
        let run = |threads: usize| {
            let pool = rayon::ThreadPoolBuilder::new().num_threads(threads).build().unwrap();
            pool.install(|| (forward(&x, rows, &w, &b, inputs), input_grad(&dy, rows, &w, inputs)))
        };
        assert_eq!(run(1), run(3));
    }
}

//! Dense layers on `matrixmultiply`'s SGEMM, row-major: the forward product and its backward,
//! shared by the MLP and the Transformer.

use rayon::prelude::*;

use crate::small;

/// Multiply-adds above which a product is split by rows over rayon's threads. Below it one
/// thread is faster: `matrixmultiply`'s own threading (which splits small products too, on
/// threads of its own beside rayon's) and a split of the columns both made the batch-1 guided
/// control step slower on 2 cores (README, Latency).
const PARALLEL_WORK: usize = 1 << 21;

/// Rows up to which a dense layer runs on the direct kernels of `small` instead of SGEMM.
const SMALL_ROWS: usize = 32;

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
    let threads = rayon::current_num_threads();
    if threads == 1 || m < 8 * threads || m * k * n < PARALLEL_WORK {
        return serial_gemm(m, k, n, a, b, c, beta);
    }
    let rows = m.div_ceil(threads);
    c[..m * n].par_chunks_mut(rows * n).enumerate().for_each(|(i, c)| {
        let block = (&a.0[i * rows * a.1 as usize..], a.1, a.2);
        serial_gemm(c.len() / n, k, n, block, b, c, beta);
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
    if rows <= SMALL_ROWS && small::available() {
        return small::forward(x, rows, w, b, inputs);
    }
    let outputs = b.len();
    debug_assert_eq!(w.len(), inputs * outputs);
    let mut y: Vec<f32> = (0..rows).flat_map(|_| b.iter().copied()).collect();
    gemm(rows, inputs, outputs, (x, inputs as isize, 1), (w, 1, inputs as isize), &mut y, 1.0);
    y
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
    if rows <= SMALL_ROWS && small::available() {
        return small::input_grad(dy, rows, w, inputs);
    }
    let outputs = w.len() / inputs;
    let mut dx = vec![0.0; rows * inputs];
    gemm(rows, outputs, inputs, (dy, outputs as isize, 1), (w, inputs as isize, 1), &mut dx, 0.0);
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
}

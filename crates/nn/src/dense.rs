//! Dense layers on `matrixmultiply`'s SGEMM, row-major: the forward product and its backward,
//! shared by the MLP and the Transformer.

/// `c = a b + beta c` for an m x k matrix `a` and a k x n matrix `b` given as (slice, row
/// stride, column stride); `c` is m x n row-major.
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
    let outputs = w.len() / inputs;
    let mut dx = vec![0.0; rows * inputs];
    gemm(rows, outputs, inputs, (dy, outputs as isize, 1), (w, inputs as isize, 1), &mut dx, 0.0);
    dx
}

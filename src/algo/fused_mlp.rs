//! A whole-MLP fused CPU engine for the training hot loops: forward, backward, the input-gradient
//! of a scalar-output MLP and the backward of a penalty on it (double backprop) — all on
//! preallocated buffers with one GEMM per layer and pass, no allocation per step. The optimiser
//! stays [`super::optim::Adam`]: the engine only computes gradients.
//!
//! Why: on 2 cores with batch 512 and hidden [256, 256], ~70% of a candle autograd step is not
//! GEMM (slow strided bias-gradient sums, ReLU masks via `ge` + `to_dtype`, zero-filled gradient
//! accumulators, optimiser temporaries; docs/performance.md). Here everything that
//! is not a GEMM is a single pass over a buffer, and the GEMMs go straight to the `gemm` crate
//! (the same kernels candle uses, AVX-512 enabled in Cargo.toml).
//!
//! Layout (as `algo::mlp::Mlp`'s vars): layer `l` maps `d[l-1] -> d[l]` with weight `W_l` stored
//! `d[l-1] x d[l]` row-major (`y = x W_l + b_l`), then its bias. ReLU after every
//! layer but the last. All parameters live in one flat `Vec<f32>` so the optimiser is one loop.
//!
//! Double backprop, hand-derived (masks `m_l = [h_l > 0]` are piecewise constant, so they carry
//! no gradient). For a scalar-output net without last bias, the input-gradient is
//! `δ_{L-1} = m_{L-1} ⊙ W_L^T`, `δ_{l-1} = m_{l-1} ⊙ (δ_l W_l^T)`, `g = δ_1 W_1^T` — exactly the
//! ordinary backward pass with upstream gradient 1. So the loss rows and the penalty rows share one
//! forward and one backward (upstream `dL/dout` on loss rows, 1 on penalty rows). Given
//! `G = dP/dg`, the penalty's weight gradients are `dW_1 += G^T δ_1`, and with
//! `e_1 = m_1 ⊙ (G W_1)`, `e_l = m_l ⊙ (e_{l-1} W_l)`: `dW_l += e_{l-1}^T δ_l` and
//! `dW_L += colsum(e_{L-1})^T`; biases get nothing from the penalty. Writing `G` and `e_l` over
//! the penalty rows of the activation buffers makes every weight gradient one GEMM over all rows:
//! `dW_l = A_{l-1}^T D_l`.

use std::time::Instant;

use gemm::Parallelism;

mod shards;
pub use shards::{EngineThreads, TrainingWorkspace};

/// Which of gemm's f32 kernels this process runs, decided as gemm decides it: `avx512f` where the
/// CPU has AVX-512 and the build the `avx512` feature, else `fma`, else `scalar`. Processes that
/// run the same kernels train bit-identical weights from the same seed and data; the kernels
/// round differently from each other (docs/fleet.md, "Determinism across machines").
pub fn gemm_kernels() -> &'static str {
    #[cfg(target_arch = "x86_64")]
    {
        if cfg!(feature = "avx512") && std::arch::is_x86_feature_detected!("avx512f") {
            return "avx512f";
        }
        if std::arch::is_x86_feature_detected!("fma") {
            return "fma";
        }
    }
    "scalar"
}

/// Which way a matrix operand is read: as stored (`N`) or transposed (`T`).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
enum Op {
    N,
    T,
}

/// `c (m x n) = [c +] op(a) · op(b)`, all row-major and contiguous; `op(a)` is `m x k` and
/// `op(b)` is `k x n`.
#[allow(clippy::too_many_arguments)]
fn matmul(
    c: &mut [f32],
    a: &[f32],
    ta: Op,
    b: &[f32],
    tb: Op,
    (m, n, k): (usize, usize, usize),
    accumulate: bool,
    par: Parallelism,
) {
    assert!(c.len() >= m * n && a.len() >= m * k && b.len() >= k * n);
    if m == 0 || n == 0 {
        return;
    }
    if k == 0 {
        if !accumulate {
            c[..m * n].fill(0.0);
        }
        return;
    }
    // (row stride, column stride) of op(a) and op(b) in their stored buffers.
    let (a_rs, a_cs) = match ta {
        Op::N => (k as isize, 1),
        Op::T => (1, m as isize),
    };
    let (b_rs, b_cs) = match tb {
        Op::N => (n as isize, 1),
        Op::T => (1, k as isize),
    };
    // SAFETY: the asserts above keep every index the strides reach inside the slices, and `c`
    // is borrowed mutably so it cannot alias `a` or `b`.
    unsafe {
        gemm::gemm(
            m,
            n,
            k,
            c.as_mut_ptr(),
            1,
            n as isize,
            accumulate,
            a.as_ptr(),
            a_cs,
            a_rs,
            b.as_ptr(),
            b_cs,
            b_rs,
            1.0,
            1.0,
            false,
            false,
            false,
            par,
        )
    }
}

/// Sum of the rows of `x` (`rows x cols`) added into `acc` (`cols`).
fn add_column_sums(acc: &mut [f32], x: &[f32], rows: usize) {
    let cols = acc.len();
    for row in x[..rows * cols].chunks_exact(cols) {
        for (a, v) in acc.iter_mut().zip(row) {
            *a += v;
        }
    }
}

/// `y (rows x out) [+]= x (rows x in) · w (in x out)`, row by row, as a sum of weight rows
/// (`y += x_i W_i`, zeros of the ReLU skipped) — the inference path. For the one-observation
/// requests of a deployed policy the GEMM kernel's set-up cost more than the arithmetic (perf:
/// 19% of a request's CPU time), and every row is summed in the same order whatever the batch, so
/// an observation gets bit-for-bit the same action alone or in a batch.
fn rows_times_weight(y: &mut [f32], x: &[f32], w: &[f32], dims: (usize, usize), accumulate: bool) {
    #[cfg(target_arch = "x86_64")]
    if std::arch::is_x86_feature_detected!("avx2") {
        // SAFETY: the CPU supports AVX2 (checked just above), all this function enables.
        return unsafe { rows_times_weight_avx2(y, x, w, dims, accumulate) };
    }
    rows_times_weight_portable(y, x, w, dims, accumulate)
}

/// The same loop compiled for AVX2 (8 lanes instead of the x86-64 baseline's 4). No FMA: the
/// sums round exactly as the portable loop's do.
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2")]
fn rows_times_weight_avx2(
    y: &mut [f32],
    x: &[f32],
    w: &[f32],
    dims: (usize, usize),
    accumulate: bool,
) {
    rows_times_weight_portable(y, x, w, dims, accumulate)
}

#[inline(always)]
fn rows_times_weight_portable(
    y: &mut [f32],
    x: &[f32],
    w: &[f32],
    (inputs, out): (usize, usize),
    accumulate: bool,
) {
    for (y_row, x_row) in y.chunks_exact_mut(out).zip(x.chunks_exact(inputs)) {
        if !accumulate {
            y_row.fill(0.0);
        }
        for (&xi, w_row) in x_row.iter().zip(w.chunks_exact(out)) {
            if xi != 0.0 {
                y_row.iter_mut().zip(w_row).for_each(|(v, &wv)| *v += xi * wv);
            }
        }
    }
}

/// The shape of an MLP: `dims = [input, hidden..., output]`, ReLU between layers.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct MlpShape {
    pub dims: Vec<usize>,
    pub last_bias: bool,
}

impl MlpShape {
    pub fn new(input: usize, hidden: &[usize], output: usize, last_bias: bool) -> Self {
        let mut dims = vec![input];
        dims.extend_from_slice(hidden);
        dims.push(output);
        Self { dims, last_bias }
    }

    pub fn layers(&self) -> usize {
        self.dims.len() - 1
    }

    fn has_bias(&self, layer: usize) -> bool {
        layer < self.layers() || self.last_bias
    }

    pub fn input(&self) -> usize {
        self.dims[0]
    }

    pub fn output(&self) -> usize {
        self.dims[self.layers()]
    }

    /// (weight offset, bias offset) of every layer `1..=L` (index 0 unused) and the total count.
    fn offsets(&self) -> (Vec<(usize, usize)>, usize) {
        let mut at = 0;
        let mut offsets = vec![(0, 0)];
        for l in 1..=self.layers() {
            let w = at;
            at += self.dims[l] * self.dims[l - 1];
            let b = at;
            if self.has_bias(l) {
                at += self.dims[l];
            }
            offsets.push((w, b));
        }
        (offsets, at)
    }

    /// Multiply-adds of one forward pass per row, times 2: the FLOPs of a forward row.
    pub fn forward_flops_per_row(&self) -> u64 {
        self.dims.windows(2).map(|w| 2 * (w[0] * w[1]) as u64).sum()
    }
}

/// An MLP's parameters, flat: per layer the weight (`in x out`, row-major), then the bias.
#[derive(Clone, Debug)]
pub struct FusedMlp {
    shape: MlpShape,
    offsets: Vec<(usize, usize)>,
    pub params: Vec<f32>,
}

impl FusedMlp {
    /// All parameters zero (to be filled, e.g. by `Mlp::copy_into_fused`).
    pub fn zeros(shape: MlpShape) -> Self {
        let (offsets, total) = shape.offsets();
        Self { shape, offsets, params: vec![0.0; total] }
    }

    pub fn shape(&self) -> &MlpShape {
        &self.shape
    }

    pub fn num_params(&self) -> usize {
        self.params.len()
    }

    fn weight(&self, l: usize) -> &[f32] {
        let (w, _) = self.offsets[l];
        &self.params[w..w + self.shape.dims[l] * self.shape.dims[l - 1]]
    }

    fn bias(&self, l: usize) -> Option<&[f32]> {
        self.shape.has_bias(l).then(|| {
            let (_, b) = self.offsets[l];
            &self.params[b..b + self.shape.dims[l]]
        })
    }
}

/// Preallocated buffers for up to `max_rows` rows through one network.
pub struct Workspace {
    max_rows: usize,
    /// Inference ([`Workspace::for_inference`]): each layer row by row, not one GEMM.
    row_by_row: bool,
    /// `acts[0]` the input, `acts[l]` layer `l`'s output (after ReLU for hidden layers).
    acts: Vec<Vec<f32>>,
    /// `deltas[l]`: gradient with respect to layer `l`'s pre-activation (index 0 unused).
    deltas: Vec<Vec<f32>>,
    /// Penalty rows: the input-gradient `g`, then the scratch for `e_l`.
    input_grad: Vec<f32>,
    scratch: Vec<f32>,
}

impl Workspace {
    /// Training buffers: every GEMM on the calling thread (a job's threads split the batch's
    /// rows between workspaces instead: [`TrainingWorkspace`]).
    fn new(shape: &MlpShape, max_rows: usize) -> Self {
        let widest = shape.dims.iter().copied().max().unwrap_or(0);
        Self {
            max_rows,
            row_by_row: false,
            acts: shape.dims.iter().map(|&d| vec![0.0; max_rows * d]).collect(),
            deltas: shape.dims.iter().map(|&d| vec![0.0; max_rows * d]).collect(),
            input_grad: vec![0.0; max_rows * shape.input()],
            scratch: vec![0.0; max_rows * widest],
        }
    }

    /// Buffers for forward passes only (inference): no gradient buffers, and each row computed
    /// on its own (see `rows_times_weight`).
    pub fn for_inference(shape: &MlpShape, max_rows: usize) -> Self {
        Self {
            max_rows,
            row_by_row: true,
            acts: shape.dims.iter().map(|&d| vec![0.0; max_rows * d]).collect(),
            deltas: Vec::new(),
            input_grad: Vec::new(),
            scratch: Vec::new(),
        }
    }

    /// The input buffer (`max_rows x input`): write the rows to evaluate here.
    pub fn input_mut(&mut self) -> &mut [f32] {
        &mut self.acts[0]
    }

    pub fn output(&self) -> &[f32] {
        self.acts.last().expect("at least one layer")
    }

    /// `dL/d output` (`max_rows x output`): the caller fills it between forward and backward.
    pub fn output_grad_mut(&mut self) -> &mut [f32] {
        self.deltas.last_mut().expect("at least one layer")
    }
}

impl FusedMlp {
    /// Forward pass on the first `rows` rows of the workspace input.
    pub fn forward(&self, ws: &mut Workspace, rows: usize) {
        assert!(rows <= ws.max_rows);
        let dims = &self.shape.dims;
        let layers = self.shape.layers();
        for l in 1..=layers {
            let (below, above) = ws.acts.split_at_mut(l);
            let (x, y) = (&below[l - 1], &mut above[0][..rows * dims[l]]);
            let accumulate = match self.bias(l) {
                Some(b) => {
                    for row in y.chunks_exact_mut(dims[l]) {
                        row.copy_from_slice(b);
                    }
                    true
                }
                None => false,
            };
            let w = self.weight(l);
            if ws.row_by_row {
                rows_times_weight(
                    y,
                    &x[..rows * dims[l - 1]],
                    w,
                    (dims[l - 1], dims[l]),
                    accumulate,
                );
            } else {
                matmul(
                    y,
                    x,
                    Op::N,
                    w,
                    Op::N,
                    (rows, dims[l], dims[l - 1]),
                    accumulate,
                    Parallelism::None,
                );
            }
            if l < layers {
                y.iter_mut().for_each(|v| *v = v.max(0.0));
            }
        }
    }

    /// Backward from `output_grad` through every layer: fills `deltas[l]` for `l = L..1` on
    /// `rows` rows (the penalty rows, if any, must hold 1 in the output gradient).
    fn backward_deltas(&self, ws: &mut Workspace, rows: usize) {
        let dims = &self.shape.dims;
        for l in (2..=self.shape.layers()).rev() {
            let (below, above) = ws.deltas.split_at_mut(l);
            let (d_in, d_out) = (&mut below[l - 1][..rows * dims[l - 1]], &above[0]);
            if dims[l] == 1 {
                // An outer product: a GEMM with k = 1 is mostly overhead.
                let w = self.weight(l);
                for (row, &d) in d_in.chunks_exact_mut(dims[l - 1]).zip(d_out) {
                    for (v, &wv) in row.iter_mut().zip(w) {
                        *v = d * wv;
                    }
                }
            } else {
                let w = self.weight(l);
                matmul(
                    d_in,
                    d_out,
                    Op::N,
                    w,
                    Op::T,
                    (rows, dims[l - 1], dims[l]),
                    false,
                    Parallelism::None,
                );
            }
            // ReLU mask of layer l-1's output, as a select so it vectorises (a conditional store
            // compiled to scalar branches took 38% of a main-loop iteration).
            for (v, &h) in d_in.iter_mut().zip(&ws.acts[l - 1]) {
                *v = if h > 0.0 { *v } else { 0.0 };
            }
        }
    }

    /// `dW_l += A_{l-1}^T D_l` over `rows` rows, `db_l += colsum(D_l)` over the first
    /// `bias_rows` rows.
    fn accumulate_param_grads(
        &self,
        ws: &Workspace,
        rows: usize,
        bias_rows: usize,
        grads: &mut [f32],
    ) {
        assert_eq!(grads.len(), self.params.len());
        let dims = &self.shape.dims;
        for l in 1..=self.shape.layers() {
            let (w, b) = self.offsets[l];
            let (dout, din) = (dims[l], dims[l - 1]);
            let dw = &mut grads[w..w + dout * din];
            matmul(
                dw,
                &ws.acts[l - 1],
                Op::T,
                &ws.deltas[l],
                Op::N,
                (din, dout, rows),
                true,
                Parallelism::None,
            );
            if self.shape.has_bias(l) {
                add_column_sums(&mut grads[b..b + dout], &ws.deltas[l], bias_rows);
            }
        }
    }

    /// One training pass on one workspace: forward on `loss_rows + penalty_rows` rows of its
    /// input (loss rows first), then
    /// - `output_grad(out, dout)`: fill `dL/d out` for the loss rows from their outputs;
    /// - `penalty(g, dp)` (only if `penalty_rows > 0`; needs a scalar output and no last bias):
    ///   given the input-gradients `g` of the penalty rows, write `dP/dg` into `dp` and return P.
    ///
    /// Accumulates `dL/dθ + dP/dθ` into `grads` and returns P (0 without penalty rows).
    /// [`TrainingWorkspace::train_pass`] runs the same steps on a job's threads.
    fn train_pass_on(
        &self,
        ws: &mut Workspace,
        (loss_rows, penalty_rows): (usize, usize),
        grads: &mut [f32],
        output_grad: impl FnOnce(&[f32], &mut [f32]),
        penalty: impl FnOnce(&[f32], &mut [f32]) -> f32,
    ) -> f32 {
        let rows = loss_rows + penalty_rows;
        let out_dim = self.shape.output();
        self.forward(ws, rows);
        {
            let (acts, deltas) = (&ws.acts, &mut ws.deltas);
            let out = &acts[self.shape.layers()][..loss_rows * out_dim];
            let dout = deltas.last_mut().expect("layers");
            output_grad(out, &mut dout[..loss_rows * out_dim]);
        }
        self.check_penalty_rows(penalty_rows);
        self.backward_deltas_from(ws, (loss_rows, penalty_rows));
        let value = if penalty_rows > 0 {
            let d0 = self.shape.input();
            let g = &ws.input_grad[..penalty_rows * d0];
            penalty(g, &mut ws.acts[0][loss_rows * d0..rows * d0])
        } else {
            0.0
        };
        self.finish_param_grads(ws, (loss_rows, penalty_rows), grads);
        value
    }

    fn check_penalty_rows(&self, penalty_rows: usize) {
        if penalty_rows > 0 {
            assert!(
                self.shape.output() == 1 && !self.shape.last_bias,
                "penalty needs a scalar critic"
            );
        }
    }

    /// After the loss rows' output gradient is in place: 1 on the penalty rows' (the
    /// input-gradient is the backward pass with upstream 1), the backward pass, and the
    /// penalty rows' input-gradient `g` into `input_grad`.
    fn backward_deltas_from(&self, ws: &mut Workspace, (loss_rows, penalty_rows): (usize, usize)) {
        let rows = loss_rows + penalty_rows;
        let out_dim = self.shape.output();
        ws.deltas.last_mut().expect("layers")[loss_rows * out_dim..rows * out_dim].fill(1.0);
        self.backward_deltas(ws, rows);
        if penalty_rows > 0 {
            self.penalty_input_grad(ws, loss_rows, penalty_rows);
        }
    }

    /// After `dP/dg` is written over the penalty rows' inputs: the `e_l` chain, then every
    /// parameter gradient accumulated into `grads`.
    fn finish_param_grads(
        &self,
        ws: &mut Workspace,
        (loss_rows, penalty_rows): (usize, usize),
        grads: &mut [f32],
    ) {
        if penalty_rows > 0 {
            self.penalty_chain(ws, loss_rows, penalty_rows);
        }
        self.accumulate_param_grads(ws, loss_rows + penalty_rows, loss_rows, grads);
    }

    /// Input-gradient `g = δ_1 W_1^T` of the `rows` penalty rows starting at `from`.
    fn penalty_input_grad(&self, ws: &mut Workspace, from: usize, rows: usize) {
        let dims = &self.shape.dims;
        let d0 = dims[0];
        let g = &mut ws.input_grad[..rows * d0];
        let delta1 = &ws.deltas[1][from * dims[1]..(from + rows) * dims[1]];
        let shape = (rows, d0, dims[1]);
        matmul(g, delta1, Op::N, self.weight(1), Op::T, shape, false, Parallelism::None);
    }

    /// The `e_l` chain written over the penalty rows of `acts`, from `G = dP/dg` over their
    /// input rows.
    fn penalty_chain(&self, ws: &mut Workspace, from: usize, rows: usize) {
        let dims = &self.shape.dims;
        for l in 1..self.shape.layers() {
            let (below, above) = ws.acts.split_at_mut(l);
            let e_prev = &below[l - 1][from * dims[l - 1]..(from + rows) * dims[l - 1]];
            let tmp = &mut ws.scratch[..rows * dims[l]];
            matmul(
                tmp,
                e_prev,
                Op::N,
                self.weight(l),
                Op::N,
                (rows, dims[l], dims[l - 1]),
                false,
                Parallelism::None,
            );
            let h = &mut above[0][from * dims[l]..(from + rows) * dims[l]];
            for (hv, &t) in h.iter_mut().zip(tmp.iter()) {
                *hv = if *hv > 0.0 { t } else { 0.0 };
            }
        }
    }
}

/// The best GFLOP/s of a few `n × n × n` f32 GEMMs (n = 1024) through [`matmul`], on `threads`
/// threads: this machine's practical peak for the kernels the engine uses, which
/// `safedice speed` reports its rates against (about 0.1 s of work at 100 GFLOP/s).
pub fn peak_gemm_gflops(threads: usize) -> f64 {
    let n = 1024;
    let a: Vec<f32> = (0..n * n).map(|i| (i % 7) as f32 * 0.01).collect();
    let b: Vec<f32> = (0..n * n).map(|i| (i % 5) as f32 * 0.01).collect();
    let mut c = vec![0f32; n * n];
    let flops = 2.0 * (n * n * n) as f64;
    let mut best = 0f64;
    // Its own pool of `threads`, as a job's engine has (rayon's global pool is candle's, one
    // thread in the service).
    let pool = rayon::ThreadPoolBuilder::new().num_threads(threads.max(1)).build();
    let par = if threads > 1 { Parallelism::Rayon(threads) } else { Parallelism::None };
    for _ in 0..6 {
        let t = Instant::now();
        match &pool {
            Ok(pool) => {
                pool.install(|| matmul(&mut c, &a, Op::N, &b, Op::N, (n, n, n), false, par))
            }
            Err(_) => matmul(&mut c, &a, Op::N, &b, Op::N, (n, n, n), false, par),
        }
        best = best.max(flops / t.elapsed().as_secs_f64() / 1e9);
    }
    std::hint::black_box(&c);
    best
}

#[cfg(test)]
mod tests {
    use candle_core::{Device, Tensor};
    use rand::{Rng, SeedableRng};
    use rand_chacha::ChaCha8Rng;

    use super::Workspace;
    use crate::algo::mlp::Mlp;

    /// The inference forward pass (row by row) agrees with candle's, with and without a last
    /// bias, and gives every row the same bits alone as in a batch.
    #[test]
    fn inference_forward_matches_candle_and_is_batch_invariant() {
        let mut rng = ChaCha8Rng::seed_from_u64(3);
        for last_bias in [true, false] {
            let mlp = Mlp::new("net", &[7, 32, 16, 3], last_bias, &Device::Cpu, &mut rng).unwrap();
            let fused = mlp.to_fused().unwrap();
            for rows in [1, 2, 5, 33] {
                let x: Vec<f32> = (0..rows * 7).map(|_| rng.random_range(-2.0..2.0)).collect();
                let want = mlp
                    .forward(&Tensor::from_vec(x.clone(), (rows, 7), &Device::Cpu).unwrap())
                    .unwrap()
                    .flatten_all()
                    .unwrap()
                    .to_vec1::<f32>()
                    .unwrap();
                let mut ws = Workspace::for_inference(fused.shape(), rows);
                ws.input_mut()[..x.len()].copy_from_slice(&x);
                fused.forward(&mut ws, rows);
                let got = &ws.output()[..rows * 3];
                for (w, g) in want.iter().zip(got) {
                    assert!((w - g).abs() < 1e-5, "rows {rows}: {w} vs {g}");
                }
                let mut one = Workspace::for_inference(fused.shape(), 1);
                one.input_mut().copy_from_slice(&x[x.len() - 7..]);
                fused.forward(&mut one, 1);
                assert_eq!(one.output(), &got[got.len() - 3..], "last row alone, rows {rows}");
            }
        }
    }
}

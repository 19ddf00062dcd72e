//! A job's threads on the fused engine: data parallelism within one training step.
//!
//! The rows of a pass (loss rows, then penalty rows) are split into `shards` contiguous parts of
//! each kind; every shard runs the forward pass, the backward pass and its share of the weight
//! gradients (`A_{l-1}^T D_l` over its own rows) on its own [`Workspace`], on one thread, with
//! no locking. Three things cannot be split by rows and run on the calling thread between the
//! parallel phases, on the whole batch gathered: the caller's loss (`output_grad`, which may
//! normalise over the batch, as Eq. 36's softmax does), the caller's penalty (`penalty`, a mean
//! over the penalty rows), and the sum of the shards' gradients, taken in shard order.
//!
//! So the arithmetic depends on the number of shards, never on which thread ran which shard or
//! how many threads there were: a job's `threads` fixes the shards and is recorded with the
//! job like its seed, and a run resumed or taken over on a machine with fewer cores computes
//! the same weights more slowly. With one shard the pass is exactly the single-threaded one.

use std::ops::Range;
use std::sync::Arc;

use rayon::prelude::*;

use super::{FusedMlp, MlpShape, Workspace};

/// Parameters per task when the shards' gradients are summed in parallel (each element is
/// still summed in shard order, so the chunking does not change the result).
const REDUCE_CHUNK: usize = 16 * 1024;

/// The threads one job computes on: `shards` fixes the arithmetic, the pool only how many of
/// the shards run at once.
#[derive(Clone)]
pub struct EngineThreads {
    shards: usize,
    pool: Option<Arc<rayon::ThreadPool>>,
}

impl std::fmt::Debug for EngineThreads {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(f, "EngineThreads {{ shards: {}, threads: {} }}", self.shards, self.threads())
    }
}

impl EngineThreads {
    /// One shard on the calling thread.
    pub fn single() -> Self {
        Self { shards: 1, pool: None }
    }

    /// `shards` shards run on a pool of `min(shards, threads)` threads (none for one).
    pub fn new(shards: usize, threads: usize) -> Result<Self, rayon::ThreadPoolBuildError> {
        let shards = shards.max(1);
        let threads = threads.clamp(1, shards);
        let pool = if threads > 1 {
            let pool = rayon::ThreadPoolBuilder::new()
                .num_threads(threads)
                .thread_name(|i| format!("safedice-engine-{i}"))
                .build()?;
            Some(Arc::new(pool))
        } else {
            None
        };
        Ok(Self { shards, pool })
    }

    pub fn shards(&self) -> usize {
        self.shards
    }

    /// Threads the shards run on.
    pub fn threads(&self) -> usize {
        self.pool.as_ref().map_or(1, |p| p.current_num_threads())
    }

    /// `f` run on the pool (on the calling thread without one). A whole pass runs inside one
    /// call, so its phases hand work to threads that are already awake: entering the pool
    /// costs a wake-up of every thread, tens of microseconds with 16 of them.
    pub fn in_pool<R: Send>(&self, f: impl FnOnce() -> R + Send) -> R {
        match &self.pool {
            Some(pool) => pool.install(f),
            None => f(),
        }
    }

    /// `f` on every item, in parallel when called inside [`EngineThreads::in_pool`] of a
    /// pool (rayon's parallel iterators run on the pool of the thread that calls them).
    pub fn for_each<T: Send>(&self, items: &mut [T], f: impl Fn(&mut T) + Sync + Send) {
        match &self.pool {
            Some(_) => items.par_iter_mut().for_each(f),
            None => items.iter_mut().for_each(f),
        }
    }

    /// `total[i] += Σ_s parts[s][i]`, summed in shard order (inside [`EngineThreads::in_pool`]).
    fn sum_into(&self, total: &mut [f32], parts: &[&[f32]]) {
        let add = |(chunk, block): (usize, &mut [f32])| {
            let start = chunk * REDUCE_CHUNK;
            for part in parts {
                let part = &part[start..start + block.len()];
                block.iter_mut().zip(part).for_each(|(t, &p)| *t += p);
            }
        };
        match &self.pool {
            Some(_) => total.par_chunks_mut(REDUCE_CHUNK).enumerate().for_each(add),
            None => total.chunks_mut(REDUCE_CHUNK).enumerate().for_each(add),
        }
    }
}

/// `0..total` in `parts` contiguous ranges whose lengths differ by at most one.
fn split_rows(total: usize, parts: usize) -> impl Iterator<Item = Range<usize>> {
    (0..parts).map(move |s| s * total / parts..(s + 1) * total / parts)
}

/// One shard: its buffers, its gradient and the rows it holds this pass.
struct Shard {
    ws: Workspace,
    grads: Vec<f32>,
    loss: Range<usize>,
    penalty: Range<usize>,
}

impl Shard {
    fn counts(&self) -> (usize, usize) {
        (self.loss.len(), self.penalty.len())
    }
}

/// Buffers for training passes of up to `max_rows` rows through one network, on a job's
/// threads ([`EngineThreads`]).
pub struct TrainingWorkspace {
    threads: EngineThreads,
    shards: Vec<Shard>,
    /// With several shards: the rows as the caller writes them, and the whole batch's outputs,
    /// output gradients, penalty input-gradients and `dP/dg` gathered between the phases.
    input: Vec<f32>,
    out: Vec<f32>,
    dout: Vec<f32>,
    g: Vec<f32>,
    dp: Vec<f32>,
}

impl TrainingWorkspace {
    pub fn new(shape: &MlpShape, max_rows: usize, threads: &EngineThreads) -> Self {
        let count = threads.shards();
        let gathered = |width: usize| if count > 1 { vec![0.0; max_rows * width] } else { vec![] };
        // A shard holds at most ⌈L/S⌉ loss and ⌈P/S⌉ penalty rows: ⌈(L+P)/S⌉ + 1.
        let shard_rows = if count > 1 { max_rows.div_ceil(count) + 1 } else { max_rows };
        let params = FusedMlp::zeros(shape.clone()).num_params();
        let shards = (0..count)
            .map(|_| Shard {
                ws: Workspace::new(shape, shard_rows),
                grads: if count > 1 { vec![0.0; params] } else { vec![] },
                loss: 0..0,
                penalty: 0..0,
            })
            .collect();
        Self {
            threads: threads.clone(),
            shards,
            input: gathered(shape.input()),
            out: gathered(shape.output()),
            dout: gathered(shape.output()),
            g: gathered(shape.input()),
            dp: gathered(shape.input()),
        }
    }

    /// The input rows (`max_rows x input`): write the loss rows, then the penalty rows, here.
    pub fn input_mut(&mut self) -> &mut [f32] {
        match self.shards.as_mut_slice() {
            [one] => one.ws.input_mut(),
            _ => &mut self.input,
        }
    }

    /// [`FusedMlp::train_pass_on`]'s pass (its arguments mean the same) over the job's
    /// threads: accumulates `dL/dθ + dP/dθ` into `grads` and returns P.
    pub fn train_pass(
        &mut self,
        net: &FusedMlp,
        rows: (usize, usize),
        grads: &mut [f32],
        output_grad: impl FnOnce(&[f32], &mut [f32]) + Send,
        penalty: impl FnOnce(&[f32], &mut [f32]) -> f32 + Send,
    ) -> f32 {
        if let [one] = self.shards.as_mut_slice() {
            return net.train_pass_on(&mut one.ws, rows, grads, output_grad, penalty);
        }
        let threads = self.threads.clone();
        threads.in_pool(|| self.sharded_pass(net, rows, grads, output_grad, penalty))
    }

    /// [`TrainingWorkspace::train_pass`] with several shards, inside the pool.
    fn sharded_pass(
        &mut self,
        net: &FusedMlp,
        (loss_rows, penalty_rows): (usize, usize),
        grads: &mut [f32],
        output_grad: impl FnOnce(&[f32], &mut [f32]),
        penalty: impl FnOnce(&[f32], &mut [f32]) -> f32,
    ) -> f32 {
        net.check_penalty_rows(penalty_rows);
        self.assign_rows(loss_rows, penalty_rows);
        self.forward(net);
        self.loss_gradient(net, loss_rows, output_grad);
        self.threads.for_each(&mut self.shards, |s| {
            let counts = s.counts();
            net.backward_deltas_from(&mut s.ws, counts);
        });
        let value = if penalty_rows > 0 { self.penalty(net, penalty_rows, penalty) } else { 0.0 };
        self.threads.for_each(&mut self.shards, |s| {
            let counts = s.counts();
            s.grads.fill(0.0);
            net.finish_param_grads(&mut s.ws, counts, &mut s.grads);
        });
        let parts: Vec<&[f32]> = self.shards.iter().map(|s| &s.grads[..]).collect();
        self.threads.sum_into(grads, &parts);
        value
    }

    fn assign_rows(&mut self, loss_rows: usize, penalty_rows: usize) {
        let count = self.shards.len();
        let ranges = split_rows(loss_rows, count).zip(split_rows(penalty_rows, count));
        for (shard, (loss, penalty)) in self.shards.iter_mut().zip(ranges) {
            shard.loss = loss;
            shard.penalty = (loss_rows + penalty.start)..(loss_rows + penalty.end);
        }
    }

    /// Each shard copies its rows in and runs the forward pass.
    fn forward(&mut self, net: &FusedMlp) {
        let (input, d) = (&self.input, net.shape().input());
        self.threads.for_each(&mut self.shards, |s| {
            let (nl, np) = s.counts();
            let own = s.ws.input_mut();
            own[..nl * d].copy_from_slice(&input[s.loss.start * d..s.loss.end * d]);
            own[nl * d..(nl + np) * d]
                .copy_from_slice(&input[s.penalty.start * d..s.penalty.end * d]);
            net.forward(&mut s.ws, nl + np);
        });
    }

    /// The loss rows' outputs gathered, the caller's loss gradient on them, scattered back.
    fn loss_gradient(
        &mut self,
        net: &FusedMlp,
        loss_rows: usize,
        output_grad: impl FnOnce(&[f32], &mut [f32]),
    ) {
        let k = net.shape().output();
        for s in &self.shards {
            let rows = s.loss.len() * k;
            self.out[s.loss.start * k..s.loss.end * k].copy_from_slice(&s.ws.output()[..rows]);
        }
        output_grad(&self.out[..loss_rows * k], &mut self.dout[..loss_rows * k]);
        for s in &mut self.shards {
            let rows = s.loss.len() * k;
            let from = &self.dout[s.loss.start * k..s.loss.end * k];
            s.ws.output_grad_mut()[..rows].copy_from_slice(from);
        }
    }

    /// The penalty rows' input-gradients gathered, the caller's penalty on them, and `dP/dg`
    /// scattered over each shard's penalty input rows. Returns P.
    fn penalty(
        &mut self,
        net: &FusedMlp,
        penalty_rows: usize,
        penalty: impl FnOnce(&[f32], &mut [f32]) -> f32,
    ) -> f32 {
        let d = net.shape().input();
        let first = self.shards[0].penalty.start;
        for s in &self.shards {
            let at = (s.penalty.start - first) * d;
            self.g[at..at + s.penalty.len() * d]
                .copy_from_slice(&s.ws.input_grad[..s.penalty.len() * d]);
        }
        let value = penalty(&self.g[..penalty_rows * d], &mut self.dp[..penalty_rows * d]);
        for s in &mut self.shards {
            let (nl, np) = s.counts();
            let at = (s.penalty.start - first) * d;
            s.ws.acts[0][nl * d..(nl + np) * d].copy_from_slice(&self.dp[at..at + np * d]);
        }
        value
    }
}

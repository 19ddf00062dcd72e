//! DWBC's equations as the paper adapts them (Appendix C.2): the negative-unlabeled
//! discriminator loss (Eq. 38) and the policy's weights (Eq. 39), each written once as candle
//! tensor code; [`super::fused`] is checked against them.

use candle_core::Tensor;

use crate::algo::losses::{neg_log_one_minus_sigmoid, neg_log_sigmoid};

/// `d` is kept in [0.1, 0.9] (its logit in ±ln 9): Eq. 38's third term, `−η E_N[−log(1 − d)]`,
/// is unbounded below otherwise (together with the first it is linear in the logit).
pub const LOGIT_CLIP: f64 = 2.197_224_577_336_219_6; // ln 9

/// Eq. 38: `η E_N[−log d] + E_U[−log(1 − d)] − η E_N[−log(1 − d)]` on clipped logits.
pub fn negative_unlabeled_loss(
    logits_n: &Tensor,
    logits_u: &Tensor,
    eta: f64,
) -> candle_core::Result<Tensor> {
    let (x_n, x_u) =
        (logits_n.clamp(-LOGIT_CLIP, LOGIT_CLIP)?, logits_u.clamp(-LOGIT_CLIP, LOGIT_CLIP)?);
    let negatives = (neg_log_sigmoid(&x_n)?.mean_all()? * eta)?;
    let unlabeled = neg_log_one_minus_sigmoid(&x_u)?.mean_all()?;
    let correction = (neg_log_one_minus_sigmoid(&x_n)?.mean_all()? * eta)?;
    (negatives + unlabeled)? - correction
}

/// Eq. 39's weights `1 − d(s, a)`, detached.
pub fn preference_weights(logits_u: &Tensor) -> candle_core::Result<Tensor> {
    let d = candle_nn::ops::sigmoid(&logits_u.clamp(-LOGIT_CLIP, LOGIT_CLIP)?)?;
    Ok(d.affine(-1.0, 1.0)?.detach())
}

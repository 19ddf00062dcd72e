//! The elementwise pieces that the algorithms' fused steps share around [`super::fused_mlp`]'s
//! GEMMs: stable softplus and sigmoid on one value, row interpolation for gradient-penalty
//! points, and the unit gradient penalty with its derivative (the host forms of
//! [`super::losses`]' tensor code).

use super::losses::GRAD_NORM_EPS;

/// `log(1 + eˣ)` without overflow (one value; the tensor form is `losses::softplus`).
pub fn softplus_f32(x: f32) -> f32 {
    x.max(0.0) + (-x.abs()).exp().ln_1p()
}

pub fn sigmoid_f32(x: f32) -> f32 {
    1.0 / (1.0 + (-x).exp())
}

/// `u·a + (1 − u)·b` row by row (`u` one value per row).
pub fn interpolate_rows(dst: &mut [f32], a: &[f32], b: &[f32], u: &[f32], dim: usize) {
    let rows = dst.chunks_exact_mut(dim).zip(a.chunks_exact(dim)).zip(b.chunks_exact(dim));
    for (((out, x), y), &t) in rows.zip(u) {
        for ((o, &xv), &yv) in out.iter_mut().zip(x).zip(y) {
            *o = t * xv + (1.0 - t) * yv;
        }
    }
}

/// `mean((‖g_r‖ − 1)²)` over the rows `g_r` (width `d`) of the penalty points' input-gradients
/// (losses::unit_gradient_penalty), and `λ ·` its derivative with respect to `g` into `dp`.
pub fn unit_penalty_and_grad(g: &[f32], dp: &mut [f32], d: usize, lambda: f32) -> f32 {
    let inv_rows = 1.0 / (g.len() / d) as f32;
    let mut total = 0.0;
    for (gr, dr) in g.chunks_exact(d).zip(dp.chunks_exact_mut(d)) {
        let norm = (gr.iter().map(|v| v * v).sum::<f32>() + GRAD_NORM_EPS as f32).sqrt();
        total += (norm - 1.0) * (norm - 1.0);
        let k = lambda * inv_rows * 2.0 * (norm - 1.0) / norm;
        for (o, &gv) in dr.iter_mut().zip(gr) {
            *o = k * gv;
        }
    }
    total * inv_rows
}

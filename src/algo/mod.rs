//! The learning algorithms on candle (no HTTP or SQL).

pub mod fused_mlp;
pub mod speed;

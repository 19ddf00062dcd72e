//! Datasets: the in-memory model, the upload parsers and their validation.

pub mod model;

pub use model::{ActionSpace, Actions, Dataset, ModelError};

//! The learning core in-process, without the server: training on the small tasks of
//! `support::tasks`, the environments and their demonstrators, `safedice datagen`, the whole
//! offline pipeline and a tiny benchmark. Memory is measured here only in child processes
//! (`memory_estimate` re-runs this binary); a test that measures its own process has a binary
//! of its own (tests/algo_memory.rs).

#[path = "../support"]
mod support {
    pub mod tasks;
}

mod bench;
mod datagen;
mod demonstrators;
mod evaluate;
mod gridworld;
mod memory_estimate;
mod pipeline;
mod safety;
mod suite;
mod training;

//! The upload parsers, writers and the canonical form. A binary of their own because the
//! property tests (`properties`) install a counting global allocator for the whole process (it
//! counts per thread, so the other tests here neither see nor disturb its figures); the
//! throughput benchmark, which times parsing and reads the process's peak memory, stays out of
//! it (tests/data_throughput.rs).

mod formats;
mod fuzz;
mod hdf5;
mod properties;
mod roundtrip;

//! Properties of the upload parsers under random damage (proptest): valid files of random
//! datasets, written by the crate's own writers (`write_jsonl`, `write_csv`, `write_npz`), are
//! mutated byte- and line-wise (bit flips, byte writes, truncations, insertions of syntax, huge
//! numbers, long runs of a byte or a pattern, random bytes, duplicated and deleted lines) and
//! parsed with `parse_file`. For every input:
//! - no panic (proptest reports a panic as a failing case and shrinks it);
//! - memory is bounded by the input: the parsing thread's peak of live heap bytes, counted by
//!   the global allocator of this test binary, stays within a small multiple of the file size
//!   plus a fixed allowance;
//! - a success is a dataset (consistent by construction) that has statistics and survives the
//!   canonical form; a rejection is a `ParseError` with a known code and a non-empty message;
//!   a writer's file without damage is never rejected;
//! - and, as a separate property, every rejection's message is at most 1 KiB.
//!
//! The same for the canonical form (`decode_canonical` of damaged `encode_canonical` bytes).
//! The seed is fixed (the same cases every run) unless PROPTEST_RNG_SEED names another, and the
//! case counts keep the binary well under a minute in a debug build.

use std::alloc::{GlobalAlloc, Layout, System};
use std::cell::Cell;
use std::path::Path;

use proptest::prelude::*;
use proptest::sample::Index;
use proptest::test_runner::{Config, RngSeed};
use safedice::data::{
    decode_canonical, encode_canonical, parse_file, stats, write_csv, write_jsonl, write_npz,
    ActionSpace, Actions, Dataset, DatasetParts, ParseError,
};

// ---------- allocation accounting ----------

/// Counts live heap bytes per thread, so that tests running in parallel do not see each
/// other's allocations. The parsers are single-threaded: the thread that calls them does all
/// their allocation.
struct CountingAllocator;

thread_local! {
    static LIVE: Cell<isize> = const { Cell::new(0) };
    static PEAK: Cell<isize> = const { Cell::new(0) };
}

fn grew(bytes: usize) {
    let _ = LIVE.try_with(|live| {
        live.set(live.get() + bytes as isize);
        let _ = PEAK.try_with(|peak| peak.set(peak.get().max(live.get())));
    });
}

fn shrank(bytes: usize) {
    let _ = LIVE.try_with(|live| live.set(live.get() - bytes as isize));
}

// SAFETY: every call is forwarded to the system allocator unchanged; the counters are
// const-initialised thread-locals without destructors, so touching them never allocates.
unsafe impl GlobalAlloc for CountingAllocator {
    unsafe fn alloc(&self, layout: Layout) -> *mut u8 {
        let ptr = System.alloc(layout);
        if !ptr.is_null() {
            grew(layout.size());
        }
        ptr
    }

    unsafe fn alloc_zeroed(&self, layout: Layout) -> *mut u8 {
        let ptr = System.alloc_zeroed(layout);
        if !ptr.is_null() {
            grew(layout.size());
        }
        ptr
    }

    unsafe fn dealloc(&self, ptr: *mut u8, layout: Layout) {
        System.dealloc(ptr, layout);
        shrank(layout.size());
    }

    unsafe fn realloc(&self, ptr: *mut u8, layout: Layout, new_size: usize) -> *mut u8 {
        let new = System.realloc(ptr, layout, new_size);
        if !new.is_null() {
            // Counted as if old and new blocks coexisted (they do while a move copies).
            grew(new_size);
            shrank(layout.size());
        }
        new
    }
}

#[global_allocator]
static ALLOCATOR: CountingAllocator = CountingAllocator;

/// Runs `f` and returns its result with the peak of heap bytes it held at once on this thread
/// (its result included).
fn peak_heap<T>(f: impl FnOnce() -> T) -> (T, usize) {
    let base = LIVE.with(Cell::get);
    PEAK.with(|peak| peak.set(base));
    let out = f();
    let peak = PEAK.with(Cell::get);
    (out, (peak - base).max(0) as usize)
}

// ---------- bounds ----------

/// Uploads: a number of two bytes in a text file ("0,") becomes an f32 of four in a column,
/// the columns grow by doubling, a missing `next_obs` is a placeholder the size of `obs`, and
/// one line is held while parsed; `write_npz` stores its arrays uncompressed, so a damaged
/// archive holds no more data than its size. A few times the input at most, then.
///
/// Not aimed at here: src/data/npz.rs reserves an array's claimed length in full before reading
/// it, so a header that damage grew to claim more than the archive holds (but less than the
/// `DecodeBudget` of src/data/flat.rs allows) is allocated at once before the read fails.
/// Random damage seldom writes such a header.
const BYTES_PER_INPUT_BYTE: usize = 16;
/// Fixed costs whatever the input: the 64 KiB read buffer of `parse_file`, the CSV reader's
/// buffers, the NPZ reader's 128 KiB chunk buffer, the first line, headers and messages.
const ALLOWANCE: usize = 512 << 10;
/// The canonical form is decoded by a bounds-checked copy per column.
const CANONICAL_BYTES_PER_INPUT_BYTE: usize = 4;
const CANONICAL_ALLOWANCE: usize = 64 << 10;
/// The longest rejection message the API should ever echo back.
const MAX_MESSAGE_BYTES: usize = 1024;

const CODES: [&str; 5] = [
    ParseError::INVALID,
    ParseError::UNKNOWN_FORMAT,
    ParseError::EMPTY,
    ParseError::UNSUPPORTED_FORMAT,
    ParseError::CORRUPT_CANONICAL,
];

// ---------- inputs ----------

/// A random valid dataset: 1 to 5 episodes of 1 to 6 transitions, distinct ids with gaps, a
/// terminal flag only on an episode's last transition, finite values of any magnitude.
fn dataset() -> impl Strategy<Value = Dataset> {
    let value = prop_oneof![
        2 => -4.0f32..4.0,
        1 => proptest::num::f32::NORMAL | proptest::num::f32::SUBNORMAL | proptest::num::f32::ZERO,
    ];
    let action = prop_oneof![(1usize..=3).prop_map(Some), Just(None)];
    let episodes = prop::collection::vec((1usize..=6, 0u32..=3), 1..=5);
    // Sometimes every action is the first one: constant dimensions get a box of their own.
    let shape = (1usize..=4, action, 1u32..=5, episodes, prop::bool::weighted(0.25));
    shape.prop_flat_map(move |(obs_dim, action_dim, discrete_n, episodes, constant)| {
        let n: usize = episodes.iter().map(|(len, _)| len).sum();
        let width = action_dim.unwrap_or(1);
        let floats = |count: usize| prop::collection::vec(value.clone(), count);
        let optional = |count: usize| prop::option::of(prop::collection::vec(value.clone(), count));
        (
            floats(n * obs_dim),
            floats(n * obs_dim),
            floats(n * width),
            prop::collection::vec(0..discrete_n, n),
            prop::collection::vec(any::<bool>(), episodes.len()),
            optional(n),
            optional(n),
        )
            .prop_map(move |(obs, next, mut cont, disc, last_terminal, rewards, costs)| {
                if constant {
                    let first = cont[..width].to_vec();
                    cont.chunks_exact_mut(width).for_each(|row| row.copy_from_slice(&first));
                }
                let (mut episode_ids, mut terminals, mut id) = (Vec::new(), Vec::new(), 0u32);
                for (k, &(len, gap)) in episodes.iter().enumerate() {
                    id += gap;
                    for i in 0..len {
                        episode_ids.push(id);
                        terminals.push(i == len - 1 && last_terminal[k]);
                    }
                    id += 1;
                }
                let (actions, action_space) = match action_dim {
                    Some(dim) => {
                        let space = ActionSpace::infer_continuous(&cont, dim);
                        (Actions::Continuous(cont), space)
                    }
                    None => {
                        (Actions::Discrete(disc), ActionSpace::Discrete { n: discrete_n as usize })
                    }
                };
                Dataset::new(DatasetParts {
                    obs_dim,
                    action_space,
                    observations: obs,
                    actions,
                    next_observations: next,
                    terminals,
                    episode_ids,
                    rewards,
                    costs,
                })
                .unwrap()
            })
    })
}

#[derive(Clone, Copy, Debug)]
enum Format {
    Jsonl,
    Csv,
    Npz,
}

impl Format {
    fn file_name(self) -> &'static str {
        match self {
            Format::Jsonl => "upload.jsonl",
            Format::Csv => "upload.csv",
            Format::Npz => "upload.npz",
        }
    }

    fn write(self, d: &Dataset, path: &Path) -> std::io::Result<()> {
        match self {
            Format::Jsonl => write_jsonl(d, path),
            Format::Csv => write_csv(d, path),
            Format::Npz => write_npz(d, path),
        }
    }
}

fn format() -> impl Strategy<Value = Format> {
    prop_oneof![Just(Format::Jsonl), Just(Format::Csv), Just(Format::Npz)]
}

#[derive(Clone, Debug)]
enum Mutation {
    FlipBit { at: Index, bit: u8 },
    SetByte { at: Index, byte: u8 },
    Truncate { at: Index },
    Insert { at: Index, bytes: Vec<u8> },
    DuplicateLine { line: Index, copies: usize },
    DeleteLine { line: Index },
}

/// What an insertion puts in: syntax, numbers no column can hold, long runs, random bytes.
fn inserted() -> impl Strategy<Value = Vec<u8>> {
    const SYNTAX: &[u8] = b"0,.-e9{}[]\n\r\"x :";
    const NUMBERS: &[&str] = &[
        "1e39",
        "-1e39",
        "1e-50",
        "4294967296",
        "18446744073709551616",
        "-1",
        "65536",
        "99999999999999999999999999999999999999999",
        "NaN",
        "Infinity",
        "1.5",
        "null",
    ];
    const PATTERNS: &[&str] = &["0,", "1e38,", "[0],", "-0.5 ", "{}", "\"a\":1,"];
    prop_oneof![
        3 => prop::sample::select(SYNTAX).prop_map(|b| vec![b]),
        3 => prop::sample::select(NUMBERS).prop_map(|s| s.as_bytes().to_vec()),
        2 => (prop::sample::select(b"x9[{ ,\n\"".as_slice()), 1usize..20_000)
            .prop_map(|(b, n)| vec![b; n]),
        2 => (prop::sample::select(PATTERNS), 1usize..5_000)
            .prop_map(|(s, n)| s.repeat(n).into_bytes()),
        2 => prop::collection::vec(any::<u8>(), 1..64),
    ]
}

fn mutation() -> impl Strategy<Value = Mutation> {
    prop_oneof![
        3 => (any::<Index>(), 0u8..8).prop_map(|(at, bit)| Mutation::FlipBit { at, bit }),
        2 => (any::<Index>(), any::<u8>()).prop_map(|(at, byte)| Mutation::SetByte { at, byte }),
        1 => any::<Index>().prop_map(|at| Mutation::Truncate { at }),
        3 => (any::<Index>(), inserted()).prop_map(|(at, bytes)| Mutation::Insert { at, bytes }),
        2 => (any::<Index>(), 1usize..40)
            .prop_map(|(line, copies)| Mutation::DuplicateLine { line, copies }),
        1 => any::<Index>().prop_map(|line| Mutation::DeleteLine { line }),
    ]
}

/// Line `k` of `bytes` as a range including its `\n` (the whole input if it has no lines).
fn line_range(bytes: &[u8], line: &Index) -> std::ops::Range<usize> {
    let mut starts = vec![0];
    starts.extend(bytes.iter().enumerate().filter(|(_, &b)| b == b'\n').map(|(i, _)| i + 1));
    starts.retain(|&s| s < bytes.len());
    let k = line.index(starts.len().max(1));
    let start = starts.get(k).copied().unwrap_or(0);
    let end = starts.get(k + 1).copied().unwrap_or(bytes.len());
    start..end
}

fn apply(mutations: &[Mutation], original: &[u8]) -> Vec<u8> {
    let mut out = original.to_vec();
    for m in mutations {
        if out.is_empty() {
            break;
        }
        match m {
            Mutation::FlipBit { at, bit } => {
                let i = at.index(out.len());
                out[i] ^= 1 << bit;
            }
            Mutation::SetByte { at, byte } => {
                let i = at.index(out.len());
                out[i] = *byte;
            }
            Mutation::Truncate { at } => out.truncate(at.index(out.len())),
            Mutation::Insert { at, bytes } => {
                let i = at.index(out.len() + 1);
                out.splice(i..i, bytes.iter().copied());
            }
            Mutation::DuplicateLine { line, copies } => {
                let range = line_range(&out, line);
                let copy = out[range.clone()].repeat(*copies);
                out.splice(range.end..range.end, copy);
            }
            Mutation::DeleteLine { line } => {
                out.drain(line_range(&out, line));
            }
        }
    }
    out
}

fn config(cases: u32) -> Config {
    let defaults = Config::default();
    Config {
        // PROPTEST_CASES / PROPTEST_RNG_SEED still choose other cases when set.
        cases: if std::env::var_os("PROPTEST_CASES").is_some() { defaults.cases } else { cases },
        rng_seed: match defaults.rng_seed {
            RngSeed::Random => RngSeed::Fixed(0x5afe_d1ce),
            seed => seed,
        },
        // A failure prints its shrunk input; nothing is written into the source tree.
        failure_persistence: None,
        ..defaults
    }
}

/// Writes `mutations` of `d` in `format` and parses it, measuring the parse's peak heap.
fn parse_damaged(
    dir: &Path,
    format: Format,
    d: &Dataset,
    mutations: &[Mutation],
) -> (Vec<u8>, Result<Dataset, ParseError>, usize) {
    let path = dir.join(format.file_name());
    format.write(d, &path).unwrap();
    let damaged = apply(mutations, &std::fs::read(&path).unwrap());
    std::fs::write(&path, &damaged).unwrap();
    let (result, peak) = peak_heap(|| parse_file(&path, format.file_name()).map(|(_, d)| d));
    (damaged, result, peak)
}

// ---------- properties ----------

proptest! {
    // Enough cases that a writer's file whose constant action dimension is huge comes up (its
    // empty box once made the NPZ reader refuse the writer's own file).
    #![proptest_config(config(1500))]

    /// No panic, bounded memory; accepted data is valid, rejections are `ParseError`s.
    #[test]
    fn damaged_uploads_are_valid_or_rejected_in_bounded_memory(
        format in format(),
        d in dataset(),
        mutations in prop::collection::vec(mutation(), 0..=3),
    ) {
        let dir = tempfile::tempdir().unwrap();
        let (input, result, peak) = parse_damaged(dir.path(), format, &d, &mutations);
        let bound = BYTES_PER_INPUT_BYTE * input.len() + ALLOWANCE;
        prop_assert!(
            peak <= bound,
            "{format:?}: {} input bytes took {peak} heap bytes at once (bound {bound})",
            input.len()
        );
        match result {
            Ok(parsed) => {
                prop_assert_eq!(stats(&parsed).transitions, parsed.len());
                // The canonical form keeps the columns; warnings live in the stats.
                let decoded = decode_canonical(&encode_canonical(&parsed)).map(Dataset::into_parts);
                prop_assert_eq!(decoded, Ok(parsed.into_parts()));
            }
            Err(e) => {
                prop_assert!(!mutations.is_empty(), "{format:?}: a writer's file was rejected: {e}");
                prop_assert!(CODES.contains(&e.code), "unknown code {}", e.code);
                prop_assert!(!e.message.is_empty());
            }
        }
    }

}

proptest! {
    #![proptest_config(config(500))]

    /// Every rejection's message is short enough to echo back in an API error, for uploads
    /// and for the canonical form alike.
    #[test]
    fn rejections_of_damaged_files_have_short_messages(
        format in prop::option::of(format()),
        d in dataset(),
        mutations in prop::collection::vec(mutation(), 1..=3),
    ) {
        let dir = tempfile::tempdir().unwrap();
        let result = match format {
            Some(format) => parse_damaged(dir.path(), format, &d, &mutations).1,
            None => decode_canonical(&apply(&mutations, &encode_canonical(&d))),
        };
        if let Err(e) = result {
            prop_assert!(
                e.message.len() <= MAX_MESSAGE_BYTES,
                "{format:?}: a {}-byte message: {:.300}...",
                e.message.len(),
                e.message
            );
        }
    }

    /// The stored canonical form, damaged (storage corruption): valid or `corrupt_canonical`,
    /// never a panic, memory bounded by the bytes.
    #[test]
    fn damaged_canonical_files_are_valid_or_corrupt_in_bounded_memory(
        d in dataset(),
        mutations in prop::collection::vec(mutation(), 1..=3),
    ) {
        let bytes = apply(&mutations, &encode_canonical(&d));
        let (result, peak) = peak_heap(|| decode_canonical(&bytes));
        let bound = CANONICAL_BYTES_PER_INPUT_BYTE * bytes.len() + CANONICAL_ALLOWANCE;
        prop_assert!(peak <= bound, "{} bytes took {peak} heap bytes (bound {bound})", bytes.len());
        match result {
            Ok(decoded) => prop_assert!(!decoded.is_empty()),
            Err(e) => {
                prop_assert_eq!(e.code, ParseError::CORRUPT_CANONICAL);
                prop_assert!(!e.message.is_empty());
            }
        }
    }
}

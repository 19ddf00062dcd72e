//! HDF5 files as D4RL and DSRL publish them (written by h5py): the keys of the flat layout
//! ([`super::flat`]) as top-level datasets, gzip- or shuffle-compressed in chunks or contiguous;
//! top-level groups (D4RL's `infos/`, `metadata/`) are not read. Read by
//! `hdf5-reader`, in Rust: no C library, in every build. Floats of any width convert to f32,
//! integers of any width to i64, and h5py's bool (an enum of int8 with FALSE = 0 and TRUE = 1)
//! to bool; any other type is refused with the key named.

use std::collections::BTreeSet;
use std::path::Path;

use hdf5_reader::{Datatype, H5Type, Hdf5File};

use super::error::ParseError;
use super::flat::{self, Array, ArrayData, ArraySource, DecodeBudget};
use super::model::Dataset;

pub fn parse(path: &Path) -> Result<Dataset, ParseError> {
    let file = Hdf5File::open(path).map_err(unreadable_file)?;
    let (groups, datasets) =
        file.root_group().and_then(|root| root.member_names()).map_err(unreadable_file)?;
    let budget = DecodeBudget::for_file(path)?;
    let mut source = Hdf5Source { file, datasets: datasets.into_iter().collect(), budget };
    let dataset = flat::assemble(&mut source)?;
    if groups.is_empty() {
        return Ok(dataset);
    }
    let names: Vec<String> = groups.iter().map(|g| format!("`{g}/`")).collect();
    Ok(dataset.with_warning(format!(
        "the file's groups {} were not read (only top-level datasets are)",
        names.join(", ")
    )))
}

fn unreadable_file(e: hdf5_reader::error::Error) -> ParseError {
    ParseError::invalid(format!("the HDF5 file is truncated or corrupt ({e})"))
}

struct Hdf5Source {
    file: Hdf5File,
    /// The top-level datasets' names.
    datasets: BTreeSet<String>,
    budget: DecodeBudget,
}

/// How an element type converts.
enum Element {
    Float(u32),
    Int { size: u32, signed: bool },
    Bool,
}

impl ArraySource for Hdf5Source {
    fn read(&mut self, key: &str) -> Result<Option<Array>, ParseError> {
        if !self.datasets.contains(key) {
            return Ok(None);
        }
        let fail = |e: hdf5_reader::error::Error| {
            ParseError::invalid(format!("key `{key}`: unreadable ({e})"))
        };
        let dataset = self.file.dataset(key).map_err(fail)?;
        let shape: Vec<usize> = dataset.shape().iter().map(|&d| d as usize).collect();
        let count = dataset.num_elements().map_err(fail)?;
        // Reads go through up to 8 bytes per element before conversion; checked before any
        // allocation, so a corrupt shape cannot ask for terabytes.
        self.budget.take(key, count, 8)?;
        let n = count as usize;
        let data = match element(key, dataset.dtype())? {
            Element::Float(4) => ArrayData::Float(read::<f32>(&dataset, n).map_err(fail)?),
            Element::Float(8) => ArrayData::Float(
                read::<f64>(&dataset, n).map_err(fail)?.into_iter().map(|v| v as f32).collect(),
            ),
            Element::Float(size) => return Err(unsupported(key, &format!("{size}-byte floats"))),
            Element::Int { size, signed } => {
                ArrayData::Int(integers(&dataset, n, size, signed).map_err(|e| match e {
                    IntError::Read(e) => fail(e),
                    IntError::Message(m) => ParseError::invalid(format!("key `{key}`: {m}")),
                })?)
            }
            Element::Bool => ArrayData::Bool(
                dataset.read_raw_bytes().map_err(fail)?.into_iter().map(|b| b != 0).collect(),
            ),
        };
        Ok(Some(Array { shape, data }))
    }
}

/// The element type of a dataset, or why it cannot be read.
fn element(key: &str, dtype: &Datatype) -> Result<Element, ParseError> {
    match dtype {
        Datatype::FloatingPoint { size, .. } => Ok(Element::Float(u32::from(*size))),
        Datatype::FixedPoint { size, signed, .. } => {
            Ok(Element::Int { size: u32::from(*size), signed: *signed })
        }
        Datatype::Enum { base, members } if is_h5py_bool(base, members) => Ok(Element::Bool),
        other => Err(unsupported(key, &format!("HDF5 type {other:?}"))),
    }
}

/// h5py stores numpy's bool as an enum over one byte with exactly FALSE = 0 and TRUE = 1.
fn is_h5py_bool(base: &Datatype, members: &[hdf5_reader::EnumMember]) -> bool {
    let one_byte = matches!(base, Datatype::FixedPoint { size: 1, .. });
    let flags = |m: &hdf5_reader::EnumMember| {
        (m.name == "FALSE" && m.value == [0]) || (m.name == "TRUE" && m.value == [1])
    };
    one_byte && members.len() == 2 && members.iter().all(flags)
}

fn unsupported(key: &str, what: &str) -> ParseError {
    ParseError::invalid(format!("key `{key}` holds {what}; expected floats, integers or bools"))
}

/// Reads exactly `n` elements stored as `T` (the reader converts byte order, never types).
fn read<T: H5Type + Copy + Default>(
    dataset: &hdf5_reader::Dataset,
    n: usize,
) -> Result<Vec<T>, hdf5_reader::error::Error> {
    let mut values = vec![T::default(); n];
    dataset.read_into(&mut values)?;
    Ok(values)
}

enum IntError {
    Read(hdf5_reader::error::Error),
    Message(String),
}

impl From<hdf5_reader::error::Error> for IntError {
    fn from(e: hdf5_reader::error::Error) -> Self {
        IntError::Read(e)
    }
}

/// Integers of any width as i64 (an unsigned 64-bit value above i64::MAX is refused).
fn integers(
    dataset: &hdf5_reader::Dataset,
    n: usize,
    size: u32,
    signed: bool,
) -> Result<Vec<i64>, IntError> {
    fn widen<T: H5Type + Copy + Default + Into<i64>>(
        dataset: &hdf5_reader::Dataset,
        n: usize,
    ) -> Result<Vec<i64>, IntError> {
        Ok(read::<T>(dataset, n)?.into_iter().map(Into::into).collect())
    }
    match (size, signed) {
        (1, true) => widen::<i8>(dataset, n),
        (2, true) => widen::<i16>(dataset, n),
        (4, true) => widen::<i32>(dataset, n),
        (8, true) => Ok(read::<i64>(dataset, n)?),
        (1, false) => widen::<u8>(dataset, n),
        (2, false) => widen::<u16>(dataset, n),
        (4, false) => widen::<u32>(dataset, n),
        (8, false) => read::<u64>(dataset, n)?
            .into_iter()
            .map(|v| {
                i64::try_from(v)
                    .map_err(|_| IntError::Message(format!("the unsigned value {v} is too large")))
            })
            .collect(),
        _ => Err(IntError::Message(format!("{size}-byte integers are not supported"))),
    }
}

//! HDF5 files (DSRL publishes its datasets this way) with the keys of the flat layout
//! ([`super::flat`]) as top-level datasets. Built only with `--features hdf5` (links libhdf5).
//! HDF5 converts stored floats/integers to the requested type on read; h5py's bool (an enum of
//! int8) reads as `bool`.

use std::path::Path;

use h5::types::TypeDescriptor;
use hdf5_metno as h5;

use super::error::ParseError;
use super::flat::{self, Array, ArrayData, ArraySource, DecodeBudget};
use super::model::Dataset;

pub fn parse(path: &Path) -> Result<Dataset, ParseError> {
    let file = h5::File::open(path)
        .map_err(|e| ParseError::invalid(format!("the HDF5 file is truncated or corrupt ({e})")))?;
    let budget = DecodeBudget::for_file(path)?;
    flat::assemble(&mut Hdf5Source { file, budget })
}

struct Hdf5Source {
    file: h5::File,
    budget: DecodeBudget,
}

impl ArraySource for Hdf5Source {
    fn read(&mut self, key: &str) -> Result<Option<Array>, ParseError> {
        if !self.file.link_exists(key) {
            return Ok(None);
        }
        let fail = |e: h5::Error| ParseError::invalid(format!("key `{key}`: unreadable ({e})"));
        let dataset = self.file.dataset(key).map_err(fail)?;
        let shape = dataset.shape();
        // Reads go through f64 / i64 (8 bytes per element) before conversion.
        self.budget.take(key, shape.iter().product::<usize>() as u64, 8)?;
        let descriptor = dataset.dtype().and_then(|t| t.to_descriptor()).map_err(fail)?;
        let data = match descriptor {
            TypeDescriptor::Float(_) => ArrayData::Float(
                dataset.read_raw::<f64>().map_err(fail)?.into_iter().map(|v| v as f32).collect(),
            ),
            TypeDescriptor::Integer(_) | TypeDescriptor::Unsigned(_) => {
                ArrayData::Int(dataset.read_raw::<i64>().map_err(fail)?)
            }
            TypeDescriptor::Boolean => ArrayData::Bool(dataset.read_raw::<bool>().map_err(fail)?),
            other => {
                return Err(ParseError::invalid(format!(
                    "key `{key}` has HDF5 type {other:?}; expected floats, integers or bools"
                )))
            }
        };
        Ok(Some(Array { shape, data }))
    }
}

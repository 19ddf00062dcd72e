//! NPZ archives (`numpy.savez` / `savez_compressed`) in the flat layout of [`super::flat`].
//! Each array's bytes are decoded in fixed-size chunks straight into its column, so memory is
//! the columns themselves; the decoded size is bounded by a [`DecodeBudget`].

use std::fs::File;
use std::io::{self, BufReader, Read};
use std::path::Path;

use npyz::npz::NpzArchive;
use npyz::{DType, Endianness, Order, TypeChar, TypeStr};

use super::error::ParseError;
use super::flat::{self, Array, ArrayData, ArraySource, DecodeBudget};
use super::model::Dataset;

pub fn parse(path: &Path) -> Result<Dataset, ParseError> {
    let budget = DecodeBudget::for_file(path)?;
    let archive = NpzArchive::open(path).map_err(|e| {
        ParseError::invalid(format!(
            "the NPZ archive is truncated or corrupt ({e}); re-create it with numpy.savez or \
             numpy.savez_compressed"
        ))
    })?;
    let mut source = NpzSource { archive, budget };
    flat::assemble(&mut source)
}

struct NpzSource {
    archive: NpzArchive<BufReader<File>>,
    budget: DecodeBudget,
}

impl ArraySource for NpzSource {
    fn read(&mut self, key: &str) -> Result<Option<Array>, ParseError> {
        let corrupt = |e: io::Error| {
            ParseError::invalid(format!(
                "key `{key}`: the array is truncated or corrupt ({e}); re-create the archive"
            ))
        };
        let Some(npy) = self.archive.by_name(key).map_err(corrupt)? else { return Ok(None) };
        let type_str = match npy.dtype() {
            DType::Plain(t) if !t.uses_pickled_array() => t,
            other => {
                return Err(ParseError::invalid(format!(
                    "key `{key}` has dtype {}; expected a numeric or bool array",
                    other.descr()
                )))
            }
        };
        let shape: Vec<usize> = npy.shape().iter().map(|&s| s as usize).collect();
        let fortran = npy.order() == Order::Fortran;
        let count: usize = shape.iter().product();
        self.budget.take(key, count as u64, type_str.size_field())?;
        let reader = npy.into_inner();
        let data = decode(key, &type_str, count, reader)?;
        let data = if fortran && shape.len() == 2 { transpose(data, &shape) } else { data };
        Ok(Some(Array { shape, data }))
    }
}

/// Decodes `count` elements of `type_str` into the matching [`ArrayData`] kind.
fn decode(key: &str, t: &TypeStr, count: usize, r: impl Read) -> Result<ArrayData, ParseError> {
    let big = t.endianness() == Endianness::Big;
    let unsupported = || {
        ParseError::invalid(format!(
            "key `{key}` has dtype {t}; expected float16/32/64, (u)int8..64 or bool"
        ))
    };
    macro_rules! ints {
        ($ty:ty) => {
            ArrayData::Int(read_elements(key, r, count, big, |b| <$ty>::from_le_bytes(b) as i64)?)
        };
    }
    Ok(match (t.type_char(), t.size_field()) {
        (TypeChar::Float, 2) => ArrayData::Float(read_elements(key, r, count, big, |b| {
            half::f16::from_le_bytes(b).to_f32()
        })?),
        (TypeChar::Float, 4) => {
            ArrayData::Float(read_elements(key, r, count, big, f32::from_le_bytes)?)
        }
        (TypeChar::Float, 8) => {
            ArrayData::Float(read_elements(key, r, count, big, |b| f64::from_le_bytes(b) as f32)?)
        }
        (TypeChar::Int, 1) => ints!(i8),
        (TypeChar::Int, 2) => ints!(i16),
        (TypeChar::Int, 4) => ints!(i32),
        (TypeChar::Int, 8) => ints!(i64),
        (TypeChar::Uint, 1) => ints!(u8),
        (TypeChar::Uint, 2) => ints!(u16),
        (TypeChar::Uint, 4) => ints!(u32),
        (TypeChar::Uint, 8) => {
            let values = read_elements(key, r, count, big, u64::from_le_bytes)?;
            if let Some(i) = values.iter().position(|&v| v > i64::MAX as u64) {
                return Err(ParseError::invalid(format!(
                    "key `{key}`: element {i} is {}, out of range",
                    values[i]
                )));
            }
            ArrayData::Int(values.into_iter().map(|v| v as i64).collect())
        }
        (TypeChar::Bool, 1) => {
            let values = read_elements(key, r, count, big, |[b]: [u8; 1]| b)?;
            if let Some(i) = values.iter().position(|&b| b > 1) {
                return Err(ParseError::invalid(format!(
                    "key `{key}`: element {i} is not a valid bool (byte {})",
                    values[i]
                )));
            }
            ArrayData::Bool(values.into_iter().map(|b| b == 1).collect())
        }
        _ => return Err(unsupported()),
    })
}

/// Reads exactly `count` elements of `N` bytes (byte-swapped first when big-endian) in chunks,
/// then checks nothing follows them.
fn read_elements<const N: usize, T>(
    key: &str,
    mut reader: impl Read,
    count: usize,
    big_endian: bool,
    convert: impl Fn([u8; N]) -> T,
) -> Result<Vec<T>, ParseError> {
    const CHUNK_ELEMENTS: usize = 16 * 1024;
    let broken = |done: usize, e: io::Error| {
        let what = if done < count {
            format!("is truncated: {done} of {count} elements could be read")
        } else {
            "is corrupt".to_string()
        };
        ParseError::invalid(format!(
            "key `{key}` {what} ({e}); the archive is incomplete or damaged, re-create it"
        ))
    };
    let mut out = Vec::with_capacity(count);
    let mut buf = vec![0u8; CHUNK_ELEMENTS * N];
    while out.len() < count {
        let take = (count - out.len()).min(CHUNK_ELEMENTS);
        let chunk = &mut buf[..take * N];
        reader.read_exact(chunk).map_err(|e| broken(out.len(), e))?;
        out.extend(chunk.chunks_exact(N).map(|c| {
            let mut bytes: [u8; N] = c.try_into().expect("chunks_exact yields N bytes");
            if big_endian {
                bytes.reverse();
            }
            convert(bytes)
        }));
    }
    // Reading to the end also makes the zip reader verify the entry's CRC.
    let mut rest = Vec::new();
    reader.read_to_end(&mut rest).map_err(|e| broken(out.len(), e))?;
    if !rest.is_empty() {
        return Err(ParseError::invalid(format!(
            "key `{key}` holds {} bytes more than its shape says; the array is corrupt",
            rest.len()
        )));
    }
    Ok(out)
}

/// Fortran-ordered (column-major) N×d data to row-major.
fn transpose(data: ArrayData, shape: &[usize]) -> ArrayData {
    fn t<T: Copy>(v: Vec<T>, rows: usize, cols: usize) -> Vec<T> {
        (0..rows * cols).map(|k| v[(k % cols) * rows + k / cols]).collect()
    }
    let (rows, cols) = (shape[0], shape[1]);
    match data {
        ArrayData::Float(v) => ArrayData::Float(t(v, rows, cols)),
        ArrayData::Int(v) => ArrayData::Int(t(v, rows, cols)),
        ArrayData::Bool(v) => ArrayData::Bool(t(v, rows, cols)),
    }
}

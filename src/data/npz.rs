//! NPZ archives (`numpy.savez` / `savez_compressed`) in the flat layout of [`super::flat`].
//! Each array's bytes are decoded in fixed-size chunks straight into its column, so memory is
//! the columns themselves; the decoded size is bounded by a [`DecodeBudget`].
//!
//! Nothing an archive declares is trusted before it is bounded: each entry's declared size is
//! checked against the budget, and an `.npy` header (whose length the file states as a u32) is
//! refused above [`MAX_NPY_HEADER_BYTES`] before a byte of it is read.

use std::fs::File;
use std::io::{self, BufReader, Cursor, Read};
use std::path::Path;

use npyz::{DType, Endianness, NpyFile, Order, TypeChar, TypeStr};
use zip::result::ZipError;
use zip::ZipArchive;

use super::error::ParseError;
use super::flat::{self, Array, ArrayData, ArraySource, DecodeBudget};
use super::model::Dataset;

/// numpy itself refuses to read headers longer than this (`max_header_size` of `numpy.load`);
/// the headers it writes are under 200 bytes.
pub const MAX_NPY_HEADER_BYTES: usize = 10_000;

pub fn parse(path: &Path) -> Result<Dataset, ParseError> {
    let budget = DecodeBudget::for_file(path)?;
    let file = File::open(path).map_err(|e| ParseError::io("opening the upload", e))?;
    let archive = ZipArchive::new(BufReader::new(file)).map_err(|e| {
        ParseError::invalid(format!(
            "the NPZ archive is truncated or corrupt ({e}); re-create it with numpy.savez or \
             numpy.savez_compressed"
        ))
    })?;
    let mut source = NpzSource { archive, budget };
    flat::assemble(&mut source)
}

struct NpzSource {
    archive: ZipArchive<BufReader<File>>,
    budget: DecodeBudget,
}

impl ArraySource for NpzSource {
    fn read(&mut self, key: &str) -> Result<Option<Array>, ParseError> {
        let corrupt = |e: io::Error| {
            ParseError::invalid(format!(
                "key `{key}`: the array is truncated or corrupt ({e}); re-create the archive"
            ))
        };
        let mut entry = match self.archive.by_name(&format!("{key}.npy")) {
            Ok(entry) => entry,
            Err(ZipError::FileNotFound) => return Ok(None),
            Err(e) => return Err(corrupt(e.into())),
        };
        self.budget.check_declared(key, entry.size())?;
        let header = read_npy_header(key, &mut entry)?;
        let npy = interpret_header(key, header, entry)?;
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
        let count = shape.iter().try_fold(1usize, |n, &d| n.checked_mul(d)).ok_or_else(|| {
            ParseError::invalid(format!("key `{key}`: shape {shape:?} overflows; corrupt file"))
        })?;
        self.budget.take(key, count as u64, type_str.size_field())?;
        let reader = npy.into_inner();
        let data = decode(key, &type_str, count, reader)?;
        let data = if fortran && shape.len() == 2 { transpose(data, &shape) } else { data };
        Ok(Some(Array { shape, data }))
    }
}

/// An entry's bytes with its already-read header put back in front.
type HeaderThen<R> = io::Chain<Cursor<Vec<u8>>, R>;

/// `npyz`'s reading of the header; a shape whose element count overflows u64 makes it panic
/// (an overflow check in its `product()`), which here is a corrupt file like any other.
fn interpret_header<R: Read>(
    key: &str,
    header: Vec<u8>,
    data: R,
) -> Result<NpyFile<HeaderThen<R>>, ParseError> {
    let parsed = std::panic::catch_unwind(std::panic::AssertUnwindSafe(|| {
        NpyFile::new(Cursor::new(header).chain(data))
    }));
    match parsed {
        Ok(Ok(npy)) => Ok(npy),
        Ok(Err(e)) => Err(ParseError::invalid(format!(
            "key `{key}`: the array is truncated or corrupt ({e}); re-create the archive"
        ))),
        Err(_) => Err(ParseError::invalid(format!(
            "key `{key}`: the .npy header declares a shape whose size overflows; corrupt file"
        ))),
    }
}

/// Reads an `.npy` preamble (magic, version, header length) and its header text, refusing a
/// declared header length above [`MAX_NPY_HEADER_BYTES`] before allocating for it. Returns the
/// bytes read, for `npyz` to interpret.
fn read_npy_header(key: &str, reader: &mut impl Read) -> Result<Vec<u8>, ParseError> {
    let not_npy = || {
        ParseError::invalid(format!(
            "key `{key}` is not an .npy array (no NUMPY magic); re-create the archive with numpy"
        ))
    };
    let mut preamble = [0u8; 12];
    reader.read_exact(&mut preamble[..10]).map_err(|_| not_npy())?;
    if &preamble[..6] != b"\x93NUMPY" {
        return Err(not_npy());
    }
    let (len_bytes, declared) = match preamble[6] {
        1 => (2, u16::from_le_bytes([preamble[8], preamble[9]]) as usize),
        2 | 3 => {
            reader.read_exact(&mut preamble[10..12]).map_err(|_| not_npy())?;
            (4, u32::from_le_bytes(preamble[8..12].try_into().expect("4 bytes")) as usize)
        }
        v => {
            return Err(ParseError::invalid(format!(
                "key `{key}`: .npy format version {v} is not supported (1, 2 or 3)"
            )))
        }
    };
    if declared > MAX_NPY_HEADER_BYTES {
        return Err(ParseError::invalid(format!(
            "key `{key}`: the .npy header declares {declared} bytes, over the limit of \
             {MAX_NPY_HEADER_BYTES} (numpy writes under 200); corrupt or malicious file"
        )));
    }
    let start = 8 + len_bytes;
    let mut header = preamble[..start].to_vec();
    header.resize(start + declared, 0);
    reader.read_exact(&mut header[start..]).map_err(|e| {
        ParseError::invalid(format!("key `{key}`: the .npy header is truncated ({e})"))
    })?;
    Ok(header)
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
    // The shape is the file's claim: grow towards it as bytes actually arrive.
    let mut out = Vec::with_capacity(count.min(CHUNK_ELEMENTS * 64));
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
    // Reading to the end makes the zip reader verify the entry's CRC; one byte is enough to
    // tell that something follows, and reading no more keeps a deflate bomb from expanding.
    let mut probe = [0u8; 1];
    let extra = loop {
        match reader.read(&mut probe) {
            Ok(n) => break n,
            Err(e) if e.kind() == io::ErrorKind::Interrupted => continue,
            Err(e) => return Err(broken(out.len(), e)),
        }
    };
    if extra > 0 {
        return Err(ParseError::invalid(format!(
            "key `{key}` holds more bytes than its {count} elements; the array is corrupt"
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

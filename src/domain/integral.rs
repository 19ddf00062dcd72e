//! Integers in JSON bodies: a number written with a zero fraction (`12.0`) is the integer it
//! equals, as JSON Schema says (`type: integer` accepts `12.0`). Bodies read through a
//! `serde_json::Value` get this rule once for the whole tree (the HTTP layer's `Json`); a type
//! read straight from the text (the action routes' bodies) asks for it per field with these
//! `deserialize_with` helpers.

use std::marker::PhantomData;

use serde::de::{Deserialize, Deserializer, Error, Unexpected, Visitor};

/// An unsigned integer (`u64`).
pub fn unsigned<'de, D: Deserializer<'de>>(d: D) -> Result<u64, D::Error> {
    d.deserialize_any(Integral(PhantomData))
}

/// A signed integer (`i64`).
pub fn signed<'de, D: Deserializer<'de>>(d: D) -> Result<i64, D::Error> {
    d.deserialize_any(Integral(PhantomData))
}

/// [`unsigned`], or null / absent (with `#[serde(default)]`).
pub fn optional_unsigned<'de, D: Deserializer<'de>>(d: D) -> Result<Option<u64>, D::Error> {
    #[derive(serde::Deserialize)]
    struct Item(#[serde(deserialize_with = "unsigned")] u64);
    Ok(Option::<Item>::deserialize(d)?.map(|Item(v)| v))
}

/// A list of [`signed`].
pub fn signed_list<'de, D: Deserializer<'de>>(d: D) -> Result<Vec<i64>, D::Error> {
    #[derive(serde::Deserialize)]
    struct Item(#[serde(deserialize_with = "signed")] i64);
    Ok(Vec::<Item>::deserialize(d)?.into_iter().map(|Item(v)| v).collect())
}

struct Integral<T>(PhantomData<T>);

impl<'de, T: TryFrom<i64> + TryFrom<u64>> Visitor<'de> for Integral<T> {
    type Value = T;

    fn expecting(&self, f: &mut std::fmt::Formatter) -> std::fmt::Result {
        write!(f, "an integer that fits {}", std::any::type_name::<T>())
    }

    fn visit_i64<E: Error>(self, v: i64) -> Result<T, E> {
        T::try_from(v).map_err(|_| E::invalid_value(Unexpected::Signed(v), &self))
    }

    fn visit_u64<E: Error>(self, v: u64) -> Result<T, E> {
        T::try_from(v).map_err(|_| E::invalid_value(Unexpected::Unsigned(v), &self))
    }

    fn visit_f64<E: Error>(self, v: f64) -> Result<T, E> {
        // 2^63 and 2^64 are exact in f64; the ranges below convert without rounding.
        if v.fract() == 0.0 && v >= -(2f64.powi(63)) && v < 2f64.powi(63) {
            self.visit_i64(v as i64)
        } else if v.fract() == 0.0 && v >= 0.0 && v < 2f64.powi(64) {
            self.visit_u64(v as u64)
        } else {
            Err(E::invalid_type(Unexpected::Float(v), &self))
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[derive(serde::Deserialize, Debug, PartialEq)]
    struct Body {
        #[serde(default, deserialize_with = "optional_unsigned")]
        size: Option<u64>,
        #[serde(default, deserialize_with = "signed_list")]
        shape: Vec<i64>,
    }

    fn read(text: &str) -> Result<Body, String> {
        serde_json::from_str(text).map_err(|e| e.to_string())
    }

    #[test]
    fn integral_floats_read_as_the_integers_they_equal() {
        assert_eq!(
            read(r#"{"size": 12.0, "shape": [1.0, -3, 4e0]}"#),
            Ok(Body { size: Some(12), shape: vec![1, -3, 4] })
        );
        assert_eq!(
            read(r#"{"size": 1.8446744073709552e19}"#).err().map(|e| e.contains("fits")),
            Some(true)
        );
        assert_eq!(read(r#"{"size": null}"#), Ok(Body { size: None, shape: vec![] }));
        assert_eq!(read("{}"), Ok(Body { size: None, shape: vec![] }));
    }

    #[test]
    fn fractions_out_of_range_values_and_other_types_are_refused() {
        for (text, says) in [
            (r#"{"size": 0.5}"#, "floating point `0.5`"),
            (r#"{"size": -1}"#, "integer `-1`"),
            (r#"{"shape": [1e300]}"#, "floating point"),
            (r#"{"shape": ["2"]}"#, "string \"2\""),
        ] {
            let error = read(text).unwrap_err();
            assert!(error.contains(says), "{text}: {error}");
        }
    }
}

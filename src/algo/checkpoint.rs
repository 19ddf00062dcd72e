//! Checkpoints: one safetensors file holding every optimiser's parameters and Adam moments, with
//! a JSON header (`__metadata__["checkpoint"]`) holding the config, the step, the RNG state, the
//! data fingerprint and the optimisers' step counts. Resuming restores all of it, so the resumed
//! run is bitwise the run that was not stopped.

use std::collections::{BTreeMap, HashMap};

use candle_core::{Device, Tensor};
use rand::SeedableRng;
use rand_chacha::ChaCha8Rng;
use serde::{Deserialize, Serialize};

use super::optim::Adam;
use super::{ResolvedConfig, TrainError};

const FORMAT: &str = "safedice-checkpoint/1";
const METADATA_KEY: &str = "checkpoint";

/// The exact position of a ChaCha8 stream.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct RngState {
    pub seed: String,
    pub stream: u64,
    /// u128 as a decimal string (JSON numbers lose precision beyond 2^53).
    pub word_pos: String,
}

impl RngState {
    pub fn of(rng: &ChaCha8Rng) -> RngState {
        RngState {
            seed: hex::encode(rng.get_seed()),
            stream: rng.get_stream(),
            word_pos: rng.get_word_pos().to_string(),
        }
    }

    pub fn rebuild(&self) -> Result<ChaCha8Rng, TrainError> {
        let bad = || TrainError::BadCheckpoint("corrupt RNG state".into());
        let seed: [u8; 32] =
            hex::decode(&self.seed).map_err(|_| bad())?.try_into().map_err(|_| bad())?;
        let mut rng = ChaCha8Rng::from_seed(seed);
        rng.set_stream(self.stream);
        rng.set_word_pos(self.word_pos.parse().map_err(|_| bad())?);
        Ok(rng)
    }
}

#[derive(Clone, Debug, Serialize, Deserialize)]
struct Header {
    format: String,
    config: ResolvedConfig,
    step: u64,
    rng: RngState,
    data_fingerprint: String,
    optimizer_steps: BTreeMap<String, u64>,
    /// A trainer's own scalars beyond its optimisers (e.g. the discriminator's early-stopping
    /// state); empty for most.
    #[serde(default, skip_serializing_if = "BTreeMap::is_empty")]
    extra: BTreeMap<String, ExactF64>,
}

/// An f64 written as the text of its shortest round-trip form (`"1.8837101022153384"`) and
/// parsed back by Rust's correctly rounded parser: serde_json's default number parser is fast
/// but may land one ulp off, and a resumed run must start from the very value it saved (the
/// early-stopping rule's best loss came back an ulp off). Checkpoints written before this
/// stored plain JSON numbers, which still read.
#[derive(Clone, Copy, Debug, PartialEq)]
struct ExactF64(f64);

impl Serialize for ExactF64 {
    fn serialize<S: serde::Serializer>(&self, serializer: S) -> Result<S::Ok, S::Error> {
        serializer.serialize_str(&format!("{:?}", self.0))
    }
}

impl<'de> Deserialize<'de> for ExactF64 {
    fn deserialize<D: serde::Deserializer<'de>>(deserializer: D) -> Result<Self, D::Error> {
        struct ExactVisitor;
        impl serde::de::Visitor<'_> for ExactVisitor {
            type Value = ExactF64;
            fn expecting(&self, f: &mut std::fmt::Formatter) -> std::fmt::Result {
                f.write_str("a number, or its text")
            }
            fn visit_str<E: serde::de::Error>(self, text: &str) -> Result<ExactF64, E> {
                text.parse()
                    .map(ExactF64)
                    .map_err(|_| E::custom(format!("{text:?} is not a number")))
            }
            fn visit_f64<E: serde::de::Error>(self, v: f64) -> Result<ExactF64, E> {
                Ok(ExactF64(v))
            }
            fn visit_i64<E: serde::de::Error>(self, v: i64) -> Result<ExactF64, E> {
                Ok(ExactF64(v as f64))
            }
            fn visit_u64<E: serde::de::Error>(self, v: u64) -> Result<ExactF64, E> {
                Ok(ExactF64(v as f64))
            }
        }
        deserializer.deserialize_any(ExactVisitor)
    }
}

/// What a trainer saves beyond its optimisers: named scalars and named tensors (stored under
/// `extra/`).
#[derive(Default)]
pub struct Extra {
    pub scalars: BTreeMap<String, f64>,
    pub tensors: Vec<(String, Tensor)>,
}

/// Serialises a run's state. `optimizers` are named (e.g. "policy", "nu"); their tensors are
/// stored as `{name}/param.*`, `{name}/m.*`, `{name}/v.*`.
pub fn encode(
    config: &ResolvedConfig,
    step: u64,
    rng: &ChaCha8Rng,
    data_fingerprint: &str,
    optimizers: &[(&str, &Adam)],
    extra: &Extra,
) -> Result<Vec<u8>, TrainError> {
    let header = Header {
        extra: extra.scalars.iter().map(|(k, &v)| (k.clone(), ExactF64(v))).collect(),
        format: FORMAT.into(),
        config: config.clone(),
        step,
        rng: RngState::of(rng),
        data_fingerprint: data_fingerprint.into(),
        optimizer_steps: optimizers.iter().map(|(n, o)| (n.to_string(), o.steps_taken())).collect(),
    };
    let mut tensors = Vec::new();
    for (name, opt) in optimizers {
        for (key, t) in opt.state() {
            tensors.push((format!("{name}/{key}"), t.to_device(&Device::Cpu)?));
        }
    }
    for (name, t) in &extra.tensors {
        tensors.push((format!("extra/{name}"), t.to_device(&Device::Cpu)?));
    }
    let metadata = HashMap::from([(
        METADATA_KEY.to_string(),
        serde_json::to_string(&header).map_err(|e| TrainError::Other(e.to_string()))?,
    )]);
    safetensors::serialize(tensors.iter().map(|(n, t)| (n.as_str(), t)), Some(metadata))
        .map_err(|e| TrainError::Other(format!("serialising checkpoint: {e}")))
}

/// A decoded checkpoint, checked against the run it is meant to continue.
pub struct Restored {
    pub step: u64,
    pub rng: ChaCha8Rng,
    tensors: HashMap<String, Tensor>,
    optimizer_steps: BTreeMap<String, u64>,
    pub extra_scalars: BTreeMap<String, f64>,
}

pub fn decode(
    bytes: &[u8],
    config: &ResolvedConfig,
    data_fingerprint: &str,
    device: &Device,
) -> Result<Restored, TrainError> {
    let bad = |m: String| TrainError::BadCheckpoint(m);
    let (_, metadata) = safetensors::SafeTensors::read_metadata(bytes)
        .map_err(|e| bad(format!("not a checkpoint ({e})")))?;
    let text = metadata
        .metadata()
        .as_ref()
        .and_then(|m| m.get(METADATA_KEY))
        .ok_or_else(|| bad("no checkpoint header".into()))?;
    let header: Header =
        serde_json::from_str(text).map_err(|e| bad(format!("corrupt header ({e})")))?;
    if header.format != FORMAT {
        return Err(bad(format!("format {} is not {FORMAT}", header.format)));
    }
    if &header.config != config {
        return Err(bad("it was made with a different config".into()));
    }
    if header.data_fingerprint != data_fingerprint {
        return Err(bad("it was made with different datasets".into()));
    }
    if header.step > config.total_steps() {
        return Err(bad(format!("step {} is past the end of the run", header.step)));
    }
    let tensors = candle_core::safetensors::load_buffer(bytes, device)
        .map_err(|e| bad(format!("corrupt tensors ({e})")))?;
    Ok(Restored {
        step: header.step,
        rng: header.rng.rebuild()?,
        tensors,
        optimizer_steps: header.optimizer_steps,
        extra_scalars: header.extra.into_iter().map(|(k, v)| (k, v.0)).collect(),
    })
}

impl Restored {
    /// The extra tensors saved with [`Extra`], by their names.
    pub fn extra_tensors(&self) -> HashMap<String, Tensor> {
        self.tensors
            .iter()
            .filter_map(|(k, t)| k.strip_prefix("extra/").map(|n| (n.to_string(), t.clone())))
            .collect()
    }

    /// Restores the optimiser saved under `name` (parameters, moments, step count).
    pub fn restore(&self, name: &str, opt: &mut Adam) -> Result<(), TrainError> {
        let t = *self
            .optimizer_steps
            .get(name)
            .ok_or_else(|| TrainError::BadCheckpoint(format!("no optimiser `{name}`")))?;
        opt.restore(&self.tensors, &format!("{name}/"), t)
            .map_err(|e| TrainError::BadCheckpoint(e.to_string()))
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use rand::Rng;

    /// Scalars go through the header's JSON: every finite f64 must read back to the same bits,
    /// or a resumed run starts from a value an ulp away (tests/http/crash_resume.rs found the
    /// early-stopping rule's best loss so; as plain JSON numbers this property fails within its
    /// 256 cases).
    fn scalar_round_trip(value: f64) -> f64 {
        let config = crate::algo::resolve_config(
            crate::algo::Algorithm::Bc,
            &serde_json::json!({"seed": 1}),
        )
        .unwrap();
        let extra =
            Extra { scalars: BTreeMap::from([("x".to_string(), value)]), tensors: Vec::new() };
        let rng = ChaCha8Rng::seed_from_u64(1);
        let bytes = encode(&config, 0, &rng, "data", &[], &extra).unwrap();
        decode(&bytes, &config, "data", &Device::Cpu).unwrap().extra_scalars["x"]
    }

    /// Checkpoints written before the scalars were text hold plain JSON numbers; they still read.
    #[test]
    fn scalars_written_as_numbers_still_read() {
        let parsed: BTreeMap<String, ExactF64> =
            serde_json::from_str(r#"{"a": 1.5, "b": 3, "c": "0.1"}"#).unwrap();
        let values: Vec<f64> = parsed.values().map(|v| v.0).collect();
        assert_eq!(values, [1.5, 3.0, 0.1]);
    }

    proptest::proptest! {
        #[test]
        fn any_finite_scalar_reads_back_bit_for_bit(bits in proptest::num::u64::ANY) {
            let value = f64::from_bits(bits);
            proptest::prop_assume!(value.is_finite());
            proptest::prop_assert_eq!(scalar_round_trip(value).to_bits(), value.to_bits());
        }
    }

    #[test]
    fn rng_state_round_trips_mid_stream() {
        let mut rng = ChaCha8Rng::seed_from_u64(42);
        for _ in 0..37 {
            rng.random::<u32>();
        }
        let state = RngState::of(&rng);
        let mut back = state.rebuild().unwrap();
        let a: Vec<u64> = (0..10).map(|_| rng.random()).collect();
        let b: Vec<u64> = (0..10).map(|_| back.random()).collect();
        assert_eq!(a, b);
    }
}

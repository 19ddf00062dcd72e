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
    extra: BTreeMap<String, f64>,
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
        extra: extra.scalars.clone(),
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
        extra_scalars: header.extra,
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
    /// or a resumed run starts from a value one ulp away (the held-out loss early stopping keeps,
    /// 1.8837101022153384, read back as ...386 before serde_json's `float_roundtrip`).
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

    #[test]
    fn checkpoint_scalars_read_back_bit_for_bit() {
        let seen = 1.883_710_102_215_338_4_f64;
        assert_eq!(scalar_round_trip(seen).to_bits(), seen.to_bits());
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

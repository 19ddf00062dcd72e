//! A trained policy as an ONNX model (opset 13), for runtimes outside the service: observations
//! in the dataset's units → the spec's observation standardisation → the MLP(s) → the
//! deterministic action in the dataset's units, exactly as [`Policy::act`] with
//! `deterministic = true`:
//!
//! - continuous: `low + (tanh(clip(mean, ±7)) + 1) / 2 · (high − low)`, output `actions`
//!   (FP32 `[B, dim]`);
//! - discrete: `argmax` of the action probabilities (softmax of the logits; DExperts' Eq. 44
//!   scores `π^U − α π^N`), output `actions` (INT64 `[B]`), and the probabilities (scores) as
//!   the second output `probabilities` (FP32 `[B, n]`);
//! - a SafeDICE policy's safety head ([`super::safety`]), as two more outputs of that action:
//!   `non_preferred_log_ratio` (the discriminator on the normalised observation and the
//!   unit-box or one-hot action, recalibrated) and `out_of_support` (the distance to the nearest
//!   reference state over the reference distance), FP32 `[B]` each.
//!
//! The protobuf messages are the `onnx-protobuf` crate's; the tensors are the policy file's
//! weights as raw little-endian FP32, written straight from the file's bytes ([`OnnxModel`]).
//!
//! [`Policy::act`]: super::Policy::act

use onnx_protobuf::attribute_proto::AttributeType;
use onnx_protobuf::tensor_proto::DataType;
use onnx_protobuf::tensor_shape_proto::{dimension, Dimension};
use onnx_protobuf::{
    type_proto, AttributeProto, GraphProto, Message, ModelProto, NodeProto, OperatorSetIdProto,
    StringStringEntryProto, TensorProto, TensorShapeProto, TypeProto, ValueInfoProto,
};
use protobuf::{EnumOrUnknown, MessageField};

use super::policy::{Decoder, PolicySpec, MEAN_CLIP};
use super::safety::{
    discriminator_prefix, Recalibration, SafetySpec, SCORE_NAMES as SAFETY_OUTPUTS, SUPPORT_TENSOR,
};
use super::TrainError;
use crate::data::ActionSpace;

/// The operator set the graph is written against (every operator used has had its current
/// form since 13).
pub const OPSET: i64 = 13;
const IR_VERSION: i64 = 8;

/// The ONNX model of a portable policy file (what `GET /v1/policies/{id}/weights` serves and
/// `safedice export` reads), the file's metadata kept in the model's metadata properties.
pub fn export_portable(file: Vec<u8>) -> Result<Vec<u8>, TrainError> {
    // Loading checks that the spec matches the tensors before the graph is built from them.
    let (_, metadata) = super::Policy::from_portable(&file)?;
    build_portable(file, &metadata)?.to_bytes()
}

/// The ONNX model of a policy from its safetensors `weights` and the portable file's metadata
/// (kept in the model's metadata properties, as [`export_portable`] does), without writing the
/// portable file or loading the policy. The model keeps `weights` and writes each tensor
/// straight from them, so building and writing it holds one copy of the weights.
pub fn build_portable(
    weights: Vec<u8>,
    metadata: &super::PortableMetadata,
) -> Result<OnnxModel, TrainError> {
    let json = serde_json::to_string(metadata).map_err(|e| TrainError::Other(e.to_string()))?;
    build(&metadata.spec, weights, &[(super::policy::PORTABLE_METADATA_KEY, json)])
}

/// An ONNX model built and not yet written: the model without its graph, the graph without the
/// policy's weight tensors, and those tensors as headers (name, type, shape) over their bytes in
/// the policy file it keeps.
///
/// It is written as one `ModelProto` whose graph field carries the graph's fields and then each
/// weight's initializer with its `raw_data` copied from the file as it is written: protobuf
/// appends a repeated field's elements in the order they come, so a reader gets the graph the
/// builder made, and no second copy of the weights exists at any time.
pub struct OnnxModel {
    model: ModelProto,
    graph: GraphProto,
    weights: Vec<(TensorProto, std::ops::Range<usize>)>,
    file: Vec<u8>,
}

/// `GraphProto.initializer`, `TensorProto.raw_data` and `ModelProto.graph`.
const GRAPH_INITIALIZER: u32 = 5;
const TENSOR_RAW_DATA: u32 = 9;
const MODEL_GRAPH: u32 = 7;

/// The size of a length-delimited field `field` of `len` bytes, with its tag and length.
fn delimited_size(field: u32, len: u64) -> u64 {
    protobuf::rt::tag_size(field) + protobuf::rt::compute_raw_varint64_size(len) + len
}

impl OnnxModel {
    /// The size of the written model in bytes.
    pub fn len(&self) -> u64 {
        self.model.compute_size() + delimited_size(MODEL_GRAPH, self.graph_len())
    }

    /// Never: a model has at least its graph.
    pub fn is_empty(&self) -> bool {
        false
    }

    fn weight_len(header: &TensorProto, raw: usize) -> u64 {
        header.compute_size() + delimited_size(TENSOR_RAW_DATA, raw as u64)
    }

    fn graph_len(&self) -> u64 {
        let weights = self.weights.iter().map(|(header, raw)| {
            delimited_size(GRAPH_INITIALIZER, Self::weight_len(header, raw.len()))
        });
        self.graph.compute_size() + weights.sum::<u64>()
    }

    /// Writes the model, for a caller that streams it rather than holding a second copy.
    pub fn write_to(&self, out: &mut dyn std::io::Write) -> Result<(), TrainError> {
        use protobuf::rt::WireType::LengthDelimited;
        let mut os = protobuf::CodedOutputStream::new(out);
        self.model.write_to(&mut os).map_err(error)?;
        os.write_tag(MODEL_GRAPH, LengthDelimited).map_err(error)?;
        os.write_raw_varint64(self.graph_len()).map_err(error)?;
        self.graph.write_to(&mut os).map_err(error)?;
        for (header, raw) in &self.weights {
            os.write_tag(GRAPH_INITIALIZER, LengthDelimited).map_err(error)?;
            os.write_raw_varint64(Self::weight_len(header, raw.len())).map_err(error)?;
            header.write_to(&mut os).map_err(error)?;
            os.write_tag(TENSOR_RAW_DATA, LengthDelimited).map_err(error)?;
            os.write_raw_varint64(raw.len() as u64).map_err(error)?;
            os.write_raw_bytes(&self.file[raw.clone()]).map_err(error)?;
        }
        os.flush().map_err(error)
    }

    pub fn to_bytes(&self) -> Result<Vec<u8>, TrainError> {
        let mut bytes = Vec::with_capacity(self.len() as usize);
        self.write_to(&mut bytes)?;
        Ok(bytes)
    }
}

/// The ONNX model of a policy: `spec` and its safetensors `weights`; `metadata` (e.g. the
/// portable file's JSON) is kept in the model's metadata properties.
pub fn export(
    spec: &PolicySpec,
    weights: Vec<u8>,
    metadata: &[(&str, String)],
) -> Result<Vec<u8>, TrainError> {
    build(spec, weights, metadata)?.to_bytes()
}

/// [`export`], built and not yet written.
pub fn build(
    spec: &PolicySpec,
    weights: Vec<u8>,
    metadata: &[(&str, String)],
) -> Result<OnnxModel, TrainError> {
    let (model, graph, placed) = build_parts(spec, &weights, metadata)?;
    Ok(OnnxModel { model, graph, weights: placed, file: weights })
}

type Parts = (ModelProto, GraphProto, Vec<(TensorProto, std::ops::Range<usize>)>);

fn build_parts(
    spec: &PolicySpec,
    file: &[u8],
    metadata: &[(&str, String)],
) -> Result<Parts, TrainError> {
    let tensors = safetensors::SafeTensors::deserialize(file).map_err(error)?;
    let mut graph =
        Graph { proto: GraphProto::new(), tensors: &tensors, file, weights: vec![], count: 0 };
    graph.proto.name = format!("safedice-{}", spec.algorithm);
    graph.proto.input.push(value_info(
        "observations",
        DataType::FLOAT,
        &[None, Some(spec.obs_dim)],
    ));
    let mut observations = "observations".to_owned();
    if let Some(norm) = &spec.observation_normalization {
        let mean = graph.constant("obs_mean", &[spec.obs_dim], &norm.mean);
        let std = graph.constant("obs_std", &[spec.obs_dim], &norm.std);
        let centred = graph.node("Sub", &[&observations, &mean], vec![]);
        observations = graph.node("Div", &[&centred, &std], vec![]);
    }
    match (&spec.action_space, &spec.decoder) {
        (ActionSpace::Continuous { dim, low, high }, _) => {
            let out = graph.mlp("policy", &observations, spec.hidden_sizes.len() + 1)?;
            let (starts, ends, axes) = (
                graph.int64s("mean_start", &[0]),
                graph.int64s("mean_end", &[*dim as i64]),
                graph.int64s("mean_axis", &[1]),
            );
            let mean = graph.node("Slice", &[&out, &starts, &ends, &axes], vec![]);
            let (lo, hi) = (
                graph.scalar("mean_min", -MEAN_CLIP as f32),
                graph.scalar("mean_max", MEAN_CLIP as f32),
            );
            let clipped = graph.node("Clip", &[&mean, &lo, &hi], vec![]);
            let unit = graph.node("Tanh", &[&clipped], vec![]);
            let half_width: Vec<f32> = low.iter().zip(high).map(|(l, h)| (h - l) * 0.5).collect();
            let centre: Vec<f32> = low.iter().zip(high).map(|(l, h)| l + (h - l) * 0.5).collect();
            let scale = graph.constant("action_half_width", &[*dim], &half_width);
            let offset = graph.constant("action_centre", &[*dim], &centre);
            let scaled = graph.node("Mul", &[&unit, &scale], vec![]);
            graph.output_node("Add", &[&scaled, &offset], "actions");
            graph.proto.output.push(value_info("actions", DataType::FLOAT, &[None, Some(*dim)]));
            if let Some(safety) = &spec.safety {
                graph.safety_outputs(safety, &observations, &unit)?;
            }
        }
        (ActionSpace::Discrete { n }, decoder) => {
            let layers = spec.hidden_sizes.len() + 1;
            let logits = graph.mlp("policy", &observations, layers)?;
            let p_u = graph.node("Softmax", &[&logits], vec![int_attribute("axis", 1)]);
            let scores = match decoder {
                Decoder::Single => p_u,
                Decoder::Dexperts { alpha } => {
                    let logits_n = graph.mlp("policy_n", &observations, layers)?;
                    let p_n = graph.node("Softmax", &[&logits_n], vec![int_attribute("axis", 1)]);
                    let alpha = graph.scalar("dexperts_alpha", *alpha as f32);
                    let weighted = graph.node("Mul", &[&p_n, &alpha], vec![]);
                    graph.node("Sub", &[&p_u, &weighted], vec![])
                }
            };
            graph.output_node("Identity", &[&scores], "probabilities");
            let argmax = vec![int_attribute("axis", 1), int_attribute("keepdims", 0)];
            graph.output_node_with("ArgMax", &[&scores], "actions", argmax);
            graph.proto.output.push(value_info("actions", DataType::INT64, &[None]));
            graph.proto.output.push(value_info(
                "probabilities",
                DataType::FLOAT,
                &[None, Some(*n)],
            ));
            if let Some(safety) = &spec.safety {
                let depth = graph.int64s("one_hot_depth", &[*n as i64]);
                let values = graph.constant("one_hot_values", &[2], &[0.0, 1.0]);
                let one_hot = graph.node("OneHot", &["actions", &depth, &values], vec![]);
                graph.safety_outputs(safety, &observations, &one_hot)?;
            }
        }
    }
    let mut model = ModelProto::new();
    model.ir_version = IR_VERSION;
    model.producer_name = "safedice".into();
    model.producer_version = env!("CARGO_PKG_VERSION").into();
    model.opset_import.push(OperatorSetIdProto { version: OPSET, ..Default::default() });
    model.metadata_props = metadata
        .iter()
        .map(|(key, value)| StringStringEntryProto {
            key: (*key).to_owned(),
            value: value.clone(),
            ..Default::default()
        })
        .collect();
    Ok((model, graph.proto, graph.weights))
}

fn error(e: impl std::fmt::Display) -> TrainError {
    TrainError::Other(format!("ONNX export: {e}"))
}

/// The graph being built, with the policy file's tensors to take weights from.
struct Graph<'a> {
    proto: GraphProto,
    tensors: &'a safetensors::SafeTensors<'a>,
    /// The bytes `tensors` reads, to place each weight in.
    file: &'a [u8],
    /// The weights' initializers without their data, and where the data is in `file`.
    weights: Vec<(TensorProto, std::ops::Range<usize>)>,
    count: usize,
}

impl Graph<'_> {
    /// A node with one fresh output; its name.
    fn node(&mut self, op: &str, inputs: &[&str], attributes: Vec<AttributeProto>) -> String {
        self.count += 1;
        let output = format!("{}_{}", op.to_lowercase(), self.count);
        self.output_node_with(op, inputs, &output, attributes);
        output
    }

    fn output_node(&mut self, op: &str, inputs: &[&str], output: &str) {
        self.output_node_with(op, inputs, output, vec![]);
    }

    fn output_node_with(
        &mut self,
        op: &str,
        inputs: &[&str],
        output: &str,
        attribute: Vec<AttributeProto>,
    ) {
        self.proto.node.push(NodeProto {
            op_type: op.into(),
            name: format!("{output}_node"),
            input: inputs.iter().map(|s| (*s).to_owned()).collect(),
            output: vec![output.to_owned()],
            attribute,
            ..Default::default()
        });
    }

    /// The MLP `{net}.{i}.weight|bias`, ReLU between layers; its output's name.
    fn mlp(&mut self, net: &str, input: &str, layers: usize) -> Result<String, TrainError> {
        self.mlp_with(net, input, layers, true)
    }

    /// [`Self::mlp`], with or without a bias on the last layer (critics have none).
    fn mlp_with(
        &mut self,
        net: &str,
        input: &str,
        layers: usize,
        last_bias: bool,
    ) -> Result<String, TrainError> {
        let mut h = input.to_owned();
        for i in 0..layers {
            let weight = self.weight(&format!("{net}.{i}.weight"))?;
            // The layers keep their weight as `[in, out]` (y = x W + b): no transpose.
            h = if i + 1 < layers || last_bias {
                let bias = self.weight(&format!("{net}.{i}.bias"))?;
                self.node("Gemm", &[&h, &weight, &bias], vec![])
            } else {
                self.node("MatMul", &[&h, &weight], vec![])
            };
            if i + 1 < layers {
                h = self.node("Relu", &[&h], vec![]);
            }
        }
        Ok(h)
    }

    /// The safety head's two outputs for the normalised `observations` and the action as the
    /// discriminator takes it (`action_input`: unit box or one-hot), as [`super::Policy`]
    /// computes them: the distances by differences, not by the expansion of the square, whose
    /// cancellation would cost digits near the data.
    fn safety_outputs(
        &mut self,
        safety: &SafetySpec,
        observations: &str,
        action_input: &str,
    ) -> Result<(), TrainError> {
        let input =
            self.node("Concat", &[observations, action_input], vec![int_attribute("axis", 1)]);
        let calibrated = self.safety_log_ratio(safety, &input)?;
        let batch = self.int64s("safety_batch_shape", &[-1]);
        self.output_node("Reshape", &[&calibrated, &batch], SAFETY_OUTPUTS[0]);
        let norm = &safety.support_normalization;
        let dim = norm.mean.len();
        let mean = self.constant("support_mean", &[dim], &norm.mean);
        let std = self.constant("support_std", &[dim], &norm.std);
        let centred = self.node("Sub", &[observations, &mean], vec![]);
        let z = self.node("Div", &[&centred, &std], vec![]);
        let axis = self.int64s("support_unsqueeze_axis", &[1]);
        let z = self.node("Unsqueeze", &[&z, &axis], vec![]);
        let reference = self.weight(SUPPORT_TENSOR)?;
        let difference = self.node("Sub", &[&z, &reference], vec![]);
        let keep = int_attribute("keepdims", 0);
        let squared = self.node(
            "ReduceSumSquare",
            &[&difference],
            vec![keep.clone(), ints_attribute("axes", &[2])],
        );
        let nearest = self.node("ReduceMin", &[&squared], vec![keep, ints_attribute("axes", &[1])]);
        let distance = self.node("Sqrt", &[&nearest], vec![]);
        let reference_distance =
            self.scalar("support_reference_distance", safety.support_reference_distance);
        self.output_node("Div", &[&distance, &reference_distance], SAFETY_OUTPUTS[1]);
        for name in SAFETY_OUTPUTS {
            self.proto.output.push(value_info(name, DataType::FLOAT, &[None]));
        }
        Ok(())
    }

    /// The safety head's log-ratio on `input`: each discriminator's recalibrated logit, summed
    /// in member order and divided by their count when there are several, as
    /// [`super::Policy`] computes it.
    fn safety_log_ratio(&mut self, safety: &SafetySpec, input: &str) -> Result<String, TrainError> {
        let layers = safety.discriminator_hidden_sizes.len() + 1;
        let own =
            Recalibration { logit_scale: safety.logit_scale, logit_shift: safety.logit_shift };
        let members: Vec<Recalibration> =
            std::iter::once(own).chain(safety.more_discriminators.iter().copied()).collect();
        let mut total: Option<String> = None;
        for (k, recalibration) in members.iter().enumerate() {
            let prefix = discriminator_prefix(k);
            let logit = self.mlp_with(&prefix, input, layers, false)?;
            let scale =
                self.scalar(&format!("{prefix}_logit_scale"), recalibration.logit_scale as f32);
            let shift =
                self.scalar(&format!("{prefix}_logit_shift"), recalibration.logit_shift as f32);
            let scaled = self.node("Mul", &[&logit, &scale], vec![]);
            let calibrated = self.node("Add", &[&scaled, &shift], vec![]);
            total = Some(match total {
                None => calibrated,
                Some(sum) => self.node("Add", &[&sum, &calibrated], vec![]),
            });
        }
        let total = total.expect("a safety head has its own discriminator");
        if members.len() == 1 {
            return Ok(total);
        }
        let count = self.scalar("safety_discriminators", members.len() as f32);
        Ok(self.node("Div", &[&total, &count], vec![]))
    }

    /// A weight of the policy file as an initializer (FP32, same shape), its data left in the
    /// file until the model is written.
    fn weight(&mut self, name: &str) -> Result<String, TrainError> {
        let view = self.tensors.tensor(name).map_err(error)?;
        if view.dtype() != safetensors::Dtype::F32 {
            return Err(error(format!("{name} is {:?}, expected F32", view.dtype())));
        }
        let mut tensor = TensorProto::new();
        tensor.name = name.to_owned();
        tensor.data_type = DataType::FLOAT as i32;
        tensor.dims = view.shape().iter().map(|&d| d as i64).collect();
        let start = view.data().as_ptr() as usize - self.file.as_ptr() as usize;
        self.weights.push((tensor, start..start + view.data().len()));
        Ok(name.to_owned())
    }

    fn constant(&mut self, name: &str, shape: &[usize], values: &[f32]) -> String {
        let mut tensor = TensorProto::new();
        tensor.name = name.to_owned();
        tensor.data_type = DataType::FLOAT as i32;
        tensor.dims = shape.iter().map(|&d| d as i64).collect();
        tensor.float_data = values.to_vec();
        self.proto.initializer.push(tensor);
        name.to_owned()
    }

    fn scalar(&mut self, name: &str, value: f32) -> String {
        self.constant(name, &[], &[value])
    }

    fn int64s(&mut self, name: &str, values: &[i64]) -> String {
        let mut tensor = TensorProto::new();
        tensor.name = name.to_owned();
        tensor.data_type = DataType::INT64 as i32;
        tensor.dims = vec![values.len() as i64];
        tensor.int64_data = values.to_vec();
        self.proto.initializer.push(tensor);
        name.to_owned()
    }
}

fn ints_attribute(name: &str, values: &[i64]) -> AttributeProto {
    AttributeProto {
        name: name.into(),
        type_: EnumOrUnknown::new(AttributeType::INTS),
        ints: values.to_vec(),
        ..Default::default()
    }
}

fn int_attribute(name: &str, value: i64) -> AttributeProto {
    AttributeProto {
        name: name.into(),
        type_: EnumOrUnknown::new(AttributeType::INT),
        i: value,
        ..Default::default()
    }
}

/// A graph input or output: its element type and shape (None: the batch dimension `B`).
fn value_info(name: &str, elem_type: DataType, shape: &[Option<usize>]) -> ValueInfoProto {
    let dim = shape
        .iter()
        .map(|d| Dimension {
            value: Some(match d {
                Some(size) => dimension::Value::DimValue(*size as i64),
                None => dimension::Value::DimParam("B".into()),
            }),
            ..Default::default()
        })
        .collect();
    let tensor = type_proto::Tensor {
        elem_type: elem_type as i32,
        shape: MessageField::some(TensorShapeProto { dim, ..Default::default() }),
        ..Default::default()
    };
    ValueInfoProto {
        name: name.into(),
        type_: MessageField::some(TypeProto {
            value: Some(type_proto::Value::TensorType(tensor)),
            ..Default::default()
        }),
        ..Default::default()
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::algo::columns::ObsNormalizer;
    use crate::algo::policy::{PolicyArtifact, PolicyNet, POLICY_FORMAT_VERSION};
    use crate::algo::Algorithm;
    use candle_core::Device;

    /// The model as one message: the graph with every weight's initializer and its data, what
    /// `write_to` streams in parts.
    fn whole(spec: &PolicySpec, file: &[u8]) -> ModelProto {
        let (mut model, mut graph, weights) =
            build_parts(spec, file, &[("k", "v".into())]).unwrap();
        for (mut header, raw) in weights {
            header.raw_data = file[raw].to_vec();
            graph.initializer.push(header);
        }
        model.graph = MessageField::some(graph);
        model
    }

    #[test]
    fn the_streamed_model_reads_back_as_the_whole_model_and_announces_its_length() {
        let cases = [
            (ActionSpace::Continuous { dim: 2, low: vec![-2.0, 0.0], high: vec![2.0, 9.0] }, 1),
            (ActionSpace::Discrete { n: 4 }, 2),
        ];
        for (space, nets) in cases {
            let decoder =
                if nets == 1 { Decoder::Single } else { Decoder::Dexperts { alpha: 0.3 } };
            let spec = PolicySpec {
                format_version: POLICY_FORMAT_VERSION,
                algorithm: Algorithm::Safedice,
                obs_dim: 3,
                action_space: space.clone(),
                hidden_sizes: vec![5, 6],
                observation_normalization: Some(ObsNormalizer {
                    mean: vec![0.5, -1.0, 2.0],
                    std: vec![2.0, 0.5, 1.0],
                }),
                decoder,
                safety: None,
            };
            let mut rng = rand::SeedableRng::seed_from_u64(3);
            let built: Vec<PolicyNet> = ["policy", "policy_n"][..nets]
                .iter()
                .map(|n| PolicyNet::new(n, 3, &[5, 6], &space, &Device::Cpu, &mut rng).unwrap())
                .collect();
            let file = PolicyArtifact::new(spec.clone(), &built.iter().collect::<Vec<_>>())
                .unwrap()
                .weights;
            let model = build(&spec, file.clone(), &[("k", "v".into())]).unwrap();
            let bytes = model.to_bytes().unwrap();
            assert_eq!(model.len(), bytes.len() as u64);
            let read = ModelProto::parse_from_bytes(&bytes).unwrap();
            assert_eq!(read, whole(&spec, &file));
            let weights = read.graph.initializer.iter().filter(|t| !t.raw_data.is_empty());
            assert_eq!(weights.count(), 3 * 2 * nets, "every layer's weight and bias");
        }
    }
}

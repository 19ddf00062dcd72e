//! Between the protocol's protobuf messages and the serving core: a `ModelInferRequest` into
//! observations and options ([`infer`]), the actions into a `ModelInferResponse`, a model's
//! description into metadata and configuration, and every error into a gRPC status
//! ([`status`]) by the same rules as REST's answers.

use std::collections::HashMap;

use tonic::{Code, Status};

use super::proto::infer_parameter::ParameterChoice;
use super::proto::model_infer_response::InferOutputTensor;
use super::proto::{
    model_metadata_response, InferParameter, InferTensorContents, ModelInferRequest,
    ModelInferResponse,
};
use crate::http::ApiError;
use crate::serving::act::ServeError;
use crate::serving::inference::{self as protocol, Input, InputData, OutputData, Served};

/// A gRPC status for an error, by REST's rules (`ApiError`: the same messages), its HTTP status
/// mapped as gRPC's HTTP mapping does; an internal error is logged and answered without detail.
pub fn status(error: impl Into<ApiError>) -> Status {
    let error = error.into();
    if let ApiError::Internal(cause) = &error {
        tracing::error!(error = ?cause, "internal error answering a gRPC call");
    }
    let code = match error.status().as_u16() {
        400 | 413 | 422 => Code::InvalidArgument,
        401 => Code::Unauthenticated,
        403 => Code::PermissionDenied,
        404 => Code::NotFound,
        408 => Code::DeadlineExceeded,
        409 => Code::FailedPrecondition,
        503 => Code::Unavailable,
        507 => Code::ResourceExhausted,
        _ => Code::Internal,
    };
    Status::new(code, error.to_string())
}

/// Actions for one `ModelInferRequest` on the model it resolved to.
pub async fn infer(
    served: &Served,
    request: ModelInferRequest,
) -> Result<ModelInferResponse, ServeError> {
    let raw = &request.raw_input_contents;
    if !raw.is_empty() && raw.len() != request.inputs.len() {
        return Err(bad_input(format!(
            "raw_input_contents has {} entries for {} inputs: send one per input, in order",
            raw.len(),
            request.inputs.len()
        )));
    }
    let mut inputs = Vec::with_capacity(request.inputs.len());
    for (i, input) in request.inputs.iter().enumerate() {
        let data = match (raw.get(i), &input.contents) {
            (Some(_), Some(_)) => {
                return Err(bad_input(format!(
                    "input `{}` has both `contents` and raw_input_contents: send one of them",
                    input.name
                )))
            }
            (Some(bytes), None) => InputData::Raw(bytes),
            (None, Some(contents)) => InputData::Fp32(fp32_contents(contents, &input.name)?),
            (None, None) => {
                InputData::Missing("has neither `contents` nor an entry in raw_input_contents")
            }
        };
        inputs.push(Input::new(&input.name, &input.datatype, &input.shape, data));
    }
    let observations = protocol::observations(inputs, served.policy.spec().obs_dim)?;
    let parameters = &request.parameters;
    // Raw output bytes unless the client asks otherwise: Triton's answer, and what
    // tritonclient.grpc reads.
    let mut raw_output = boolean(parameters, "binary_data_output")?.unwrap_or(true);
    for output in &request.outputs {
        if let Some(binary) = boolean(&output.parameters, "binary_data")? {
            raw_output = binary;
        }
    }
    let requested: Vec<&str> = request.outputs.iter().map(|o| o.name.as_str()).collect();
    let policy = &served.policy;
    let safety_score = boolean(parameters, "safety_score")?;
    let wanted = protocol::wanted_outputs(&requested, safety_score, policy)?;
    let deterministic = boolean(parameters, "deterministic")?.unwrap_or(true);
    let outputs =
        protocol::infer(served, observations, deterministic, seed(parameters)?, &wanted).await?;
    let mut tensors = Vec::with_capacity(outputs.len());
    let mut raw_output_contents = Vec::new();
    for output in outputs {
        let mut tensor = InferOutputTensor {
            name: output.name.into(),
            datatype: output.datatype.into(),
            shape: output.shape,
            ..Default::default()
        };
        if raw_output {
            raw_output_contents.push(output.data.little_endian().into());
        } else {
            tensor.contents = Some(match output.data {
                OutputData::Fp32(fp32_contents) => {
                    InferTensorContents { fp32_contents, ..Default::default() }
                }
                OutputData::Int64(int64_contents) => {
                    InferTensorContents { int64_contents, ..Default::default() }
                }
            });
        }
        tensors.push(tensor);
    }
    Ok(ModelInferResponse {
        model_name: served.name.clone(),
        model_version: served.version.clone(),
        id: request.id,
        parameters: HashMap::new(),
        outputs: tensors,
        raw_output_contents,
    })
}

/// An FP32 input's typed values: `fp32_contents`, and no other kind.
fn fp32_contents(contents: &InferTensorContents, input: &str) -> Result<Vec<f32>, ServeError> {
    let others = !contents.bool_contents.is_empty()
        || !contents.int_contents.is_empty()
        || !contents.int64_contents.is_empty()
        || !contents.uint_contents.is_empty()
        || !contents.uint64_contents.is_empty()
        || !contents.fp64_contents.is_empty()
        || !contents.bytes_contents.is_empty();
    if others {
        return Err(bad_input(format!(
            "input `{input}` is FP32: send its values in `contents.fp32_contents` (or as \
             raw_input_contents)"
        )));
    }
    Ok(contents.fp32_contents.clone())
}

/// A bool parameter, if present.
fn boolean(
    parameters: &HashMap<String, InferParameter>,
    name: &str,
) -> Result<Option<bool>, ServeError> {
    match parameters.get(name).and_then(|p| p.parameter_choice.as_ref()) {
        None => Ok(None),
        Some(ParameterChoice::BoolParam(value)) => Ok(Some(*value)),
        Some(_) => Err(bad_parameter(format!("parameter `{name}` must be a bool_param"))),
    }
}

/// The `seed` parameter (int64 or uint64, at most 2^63 - 1, as `/act` takes it).
fn seed(parameters: &HashMap<String, InferParameter>) -> Result<Option<u64>, ServeError> {
    let out_of_range =
        || bad_parameter("parameter `seed` must be an integer from 0 to 2^63 - 1".to_owned());
    match parameters.get("seed").and_then(|p| p.parameter_choice.as_ref()) {
        None => Ok(None),
        Some(ParameterChoice::Int64Param(seed)) => {
            u64::try_from(*seed).map(Some).map_err(|_| out_of_range())
        }
        Some(ParameterChoice::Uint64Param(seed)) if i64::try_from(*seed).is_ok() => Ok(Some(*seed)),
        Some(_) => Err(out_of_range()),
    }
}

fn bad_input(message: String) -> ServeError {
    ServeError::invalid("invalid_input", message)
}

fn bad_parameter(message: String) -> ServeError {
    ServeError::invalid("invalid_parameters", message)
}

/// A tensor of model metadata.
pub fn tensor_metadata(tensor: protocol::Tensor) -> model_metadata_response::TensorMetadata {
    model_metadata_response::TensorMetadata {
        name: tensor.name.into(),
        datatype: tensor.datatype.into(),
        shape: tensor.shape,
    }
}

/// Triton's `DataType` of a protocol datatype (`FP32` → `TYPE_FP32`).
pub fn config_type(datatype: &str) -> i32 {
    use super::proto::DataType;
    match datatype {
        "FP32" => DataType::TypeFp32,
        "INT64" => DataType::TypeInt64,
        _ => DataType::TypeInvalid,
    }
    .into()
}

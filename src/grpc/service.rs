//! `inference.GRPCInferenceService`: each RPC checks the caller's token as REST does, runs
//! through the serving core ([`crate::serving::inference`]) and is counted in the metrics.

use std::collections::HashMap;
use std::future::Future;
use std::pin::Pin;
use std::sync::Arc;
use std::time::Instant;

use futures::Stream;
use tokio::sync::{OwnedSemaphorePermit, Semaphore};
use tonic::metadata::MetadataMap;
use tonic::{Request, Response, Status, Streaming};

use super::convert::{self, status};
use super::proto::grpc_inference_service_server::GrpcInferenceService;
use super::proto::*;
use crate::http::auth::{Refusal, Requirement};
use crate::http::{ApiError, AppState, REQUEST_TIMEOUT};
use crate::serving::inference::{self as protocol, statistics, Served};

/// The metadata key of a client's request key: requests (or a whole stream) with the same key
/// get the same side of a canary, as REST's `x-safedice-request-key` header.
pub const REQUEST_KEY: &str = "x-safedice-request-key";

/// The service, on the same state as the HTTP API.
pub struct Inference {
    state: AppState,
    /// One permit per open `ModelStreamInfer` stream (`--grpc-max-streams`).
    streams: Arc<Semaphore>,
}

impl Inference {
    pub fn new(state: AppState) -> Self {
        let streams = Arc::new(Semaphore::new(state.config.grpc_max_streams as usize));
        Inference { state, streams }
    }

    /// A stream's permit, held until the stream ends; RESOURCE_EXHAUSTED at the cap.
    fn stream_permit(&self) -> Result<OwnedSemaphorePermit, Status> {
        self.streams.clone().try_acquire_owned().map_err(|_| {
            Status::resource_exhausted(format!(
                "{} ModelStreamInfer streams are open on this server, its cap \
                 (--grpc-max-streams): retry when one closes, or call ModelInfer",
                self.state.config.grpc_max_streams
            ))
        })
    }

    /// Lets the call through if its `authorization: Bearer <token>` allows `required`.
    fn authorize(&self, metadata: &MetadataMap, required: Requirement) -> Result<(), Status> {
        let presented = metadata
            .get("authorization")
            .and_then(|v| v.to_str().ok())
            .and_then(crate::http::auth::bearer);
        self.state.tokens.authorize(presented, required).map_err(|refusal| match refusal {
            Refusal::Missing => Status::unauthenticated(
                "this call needs a bearer token: send the metadata `authorization: Bearer <token>`",
            ),
            Refusal::Invalid => {
                Status::unauthenticated("the bearer token is not valid for this server")
            }
            Refusal::InferenceOnly => Status::permission_denied(
                "the inference token may not call the repository (RepositoryIndex, \
                 RepositoryModelLoad, RepositoryModelUnload); use the API token",
            ),
        })
    }

    /// Runs a unary call: the token checked, `work` bounded by REST's request timeout, the call
    /// counted by method and status code.
    async fn call<T>(
        &self,
        method: &'static str,
        metadata: &MetadataMap,
        required: Requirement,
        work: impl Future<Output = Result<T, Status>>,
    ) -> Result<Response<T>, Status> {
        let started = Instant::now();
        let result = match self.authorize(metadata, required) {
            Ok(()) => bounded(work).await,
            Err(refused) => Err(refused),
        };
        observe(&self.state, method, &result, started);
        result.map(Response::new)
    }

    async fn served(
        &self,
        name: String,
        version: String,
        key: Option<&str>,
    ) -> Result<Served, Status> {
        let version = (!version.is_empty()).then_some(version);
        protocol::served(&self.state.serving, name, version, key).await.map_err(status)
    }
}

/// `work`, or UNAVAILABLE once it has taken REST's request timeout.
async fn bounded<T>(work: impl Future<Output = Result<T, Status>>) -> Result<T, Status> {
    match tokio::time::timeout(REQUEST_TIMEOUT, work).await {
        Ok(result) => result,
        Err(_) => Err(status(ApiError::unavailable(
            "timeout",
            format!(
                "the request took longer than {} s and was abandoned",
                REQUEST_TIMEOUT.as_secs()
            ),
        ))),
    }
}

fn observe<T>(
    state: &AppState,
    method: &'static str,
    result: &Result<T, Status>,
    started: Instant,
) {
    let code = match result {
        Ok(_) => "OK",
        Err(status) => code_name(status.code()),
    };
    state.metrics.observe_grpc(method, code, started.elapsed().as_secs_f64());
}

/// The status code's name as gRPC spells it.
fn code_name(code: tonic::Code) -> &'static str {
    use tonic::Code::*;
    match code {
        Ok => "OK",
        Cancelled => "CANCELLED",
        Unknown => "UNKNOWN",
        InvalidArgument => "INVALID_ARGUMENT",
        DeadlineExceeded => "DEADLINE_EXCEEDED",
        NotFound => "NOT_FOUND",
        AlreadyExists => "ALREADY_EXISTS",
        PermissionDenied => "PERMISSION_DENIED",
        ResourceExhausted => "RESOURCE_EXHAUSTED",
        FailedPrecondition => "FAILED_PRECONDITION",
        Aborted => "ABORTED",
        OutOfRange => "OUT_OF_RANGE",
        Unimplemented => "UNIMPLEMENTED",
        Internal => "INTERNAL",
        Unavailable => "UNAVAILABLE",
        DataLoss => "DATA_LOSS",
        Unauthenticated => "UNAUTHENTICATED",
    }
}

fn request_key(metadata: &MetadataMap) -> Option<String> {
    metadata.get(REQUEST_KEY).and_then(|v| v.to_str().ok()).map(str::to_owned)
}

/// One inference on the model the request names, counted in its version's statistics.
async fn infer_once(
    state: &AppState,
    request: ModelInferRequest,
    key: Option<&str>,
) -> Result<ModelInferResponse, Status> {
    let version = (!request.model_version.is_empty()).then(|| request.model_version.clone());
    let served = protocol::served(&state.serving, request.model_name.clone(), version, key)
        .await
        .map_err(status)?;
    served.timed(convert::infer(&served, request)).await.map_err(status)
}

type InferStream = Pin<Box<dyn Stream<Item = Result<ModelStreamInferResponse, Status>> + Send>>;

#[tonic::async_trait]
impl GrpcInferenceService for Inference {
    async fn server_live(
        &self,
        request: Request<ServerLiveRequest>,
    ) -> Result<Response<ServerLiveResponse>, Status> {
        self.call("ServerLive", request.metadata(), Requirement::Action, async {
            Ok(ServerLiveResponse { live: true })
        })
        .await
    }

    async fn server_ready(
        &self,
        request: Request<ServerReadyRequest>,
    ) -> Result<Response<ServerReadyResponse>, Status> {
        // Not ready (the database does not answer) is an answer, as Triton gives it.
        self.call("ServerReady", request.metadata(), Requirement::Action, async {
            Ok(ServerReadyResponse { ready: self.state.store.ping().await.is_ok() })
        })
        .await
    }

    async fn model_ready(
        &self,
        request: Request<ModelReadyRequest>,
    ) -> Result<Response<ModelReadyResponse>, Status> {
        let (metadata, _, message) = request.into_parts();
        self.call("ModelReady", &metadata, Requirement::Action, async {
            self.served(message.name, message.version, None).await?;
            Ok(ModelReadyResponse { ready: true })
        })
        .await
    }

    async fn server_metadata(
        &self,
        request: Request<ServerMetadataRequest>,
    ) -> Result<Response<ServerMetadataResponse>, Status> {
        self.call("ServerMetadata", request.metadata(), Requirement::Action, async {
            Ok(ServerMetadataResponse {
                name: "safedice".into(),
                version: env!("CARGO_PKG_VERSION").into(),
                extensions: protocol::EXTENSIONS.map(String::from).to_vec(),
            })
        })
        .await
    }

    async fn model_metadata(
        &self,
        request: Request<ModelMetadataRequest>,
    ) -> Result<Response<ModelMetadataResponse>, Status> {
        let (metadata, _, message) = request.into_parts();
        self.call("ModelMetadata", &metadata, Requirement::Action, async {
            let model = self.served(message.name, message.version, None).await?.describe();
            Ok(ModelMetadataResponse {
                name: model.name,
                versions: model.versions,
                platform: protocol::PLATFORM.into(),
                inputs: vec![convert::tensor_metadata(model.input)],
                outputs: model.outputs.into_iter().map(convert::tensor_metadata).collect(),
            })
        })
        .await
    }

    async fn model_infer(
        &self,
        request: Request<ModelInferRequest>,
    ) -> Result<Response<ModelInferResponse>, Status> {
        let (metadata, _, message) = request.into_parts();
        let key = request_key(&metadata);
        self.call("ModelInfer", &metadata, Requirement::Action, async {
            infer_once(&self.state, message, key.as_deref()).await
        })
        .await
    }

    type ModelStreamInferStream = InferStream;

    /// One response per request, in order; a request that fails answers its error in
    /// `error_message` and the stream goes on. The stream ends when the client closes its side,
    /// and at the server's shutdown.
    async fn model_stream_infer(
        &self,
        request: Request<Streaming<ModelInferRequest>>,
    ) -> Result<Response<Self::ModelStreamInferStream>, Status> {
        let (metadata, _, incoming) = request.into_parts();
        if let Err(refused) = self.authorize(&metadata, Requirement::Action) {
            observe::<()>(&self.state, "ModelStreamInfer", &Err(refused.clone()), Instant::now());
            return Err(refused);
        }
        let permit = match self.stream_permit() {
            Ok(permit) => permit,
            Err(refused) => {
                observe::<()>(
                    &self.state,
                    "ModelStreamInfer",
                    &Err(refused.clone()),
                    Instant::now(),
                );
                return Err(refused);
            }
        };
        let key = request_key(&metadata);
        let state = self.state.clone();
        // The permit lives in the stream's state: it is released when the stream is dropped.
        let stream = futures::stream::unfold(Some((incoming, permit)), move |open| {
            let (state, key) = (state.clone(), key.clone());
            async move {
                let (mut incoming, permit) = open?;
                let received = tokio::select! {
                    received = incoming.message() => received,
                    () = state.shutdown.cancelled() => return None,
                };
                let request = match received {
                    Ok(Some(request)) => request,
                    Ok(None) => return None,
                    // The client's side broke (a message over the size limit, a reset): the
                    // stream ends with its status.
                    Err(broken) => return Some((Err(broken), None)),
                };
                let started = Instant::now();
                let (id, model_name) = (request.id.clone(), request.model_name.clone());
                let result = bounded(infer_once(&state, request, key.as_deref())).await;
                observe(&state, "ModelStreamInfer", &result, started);
                let response = match result {
                    Ok(response) => ModelStreamInferResponse {
                        error_message: String::new(),
                        infer_response: Some(response),
                    },
                    Err(failed) => ModelStreamInferResponse {
                        error_message: failed.message().to_owned(),
                        infer_response: Some(ModelInferResponse {
                            model_name,
                            id,
                            ..Default::default()
                        }),
                    },
                };
                Some((Ok(response), Some((incoming, permit))))
            }
        });
        Ok(Response::new(Box::pin(stream)))
    }

    async fn model_config(
        &self,
        request: Request<ModelConfigRequest>,
    ) -> Result<Response<ModelConfigResponse>, Status> {
        let (metadata, _, message) = request.into_parts();
        self.call("ModelConfig", &metadata, Requirement::Action, async {
            let model = self.served(message.name, message.version, None).await?.describe();
            let parameter = |value: String| ModelParameter { string_value: value };
            let config = ModelConfig {
                name: model.name,
                platform: protocol::PLATFORM.into(),
                backend: protocol::PLATFORM.into(),
                max_batch_size: 0,
                input: vec![ModelInput {
                    name: model.input.name.into(),
                    data_type: convert::config_type(model.input.datatype),
                    dims: model.input.shape,
                }],
                output: model
                    .outputs
                    .into_iter()
                    .map(|output| ModelOutput {
                        name: output.name.into(),
                        data_type: convert::config_type(output.datatype),
                        dims: output.shape,
                    })
                    .collect(),
                parameters: HashMap::from([
                    ("algorithm".to_owned(), parameter(model.algorithm)),
                    ("version".to_owned(), parameter(model.version)),
                ]),
            };
            Ok(ModelConfigResponse { config: Some(config) })
        })
        .await
    }

    async fn model_statistics(
        &self,
        request: Request<ModelStatisticsRequest>,
    ) -> Result<Response<ModelStatisticsResponse>, Status> {
        let (metadata, _, message) = request.into_parts();
        self.call("ModelStatistics", &metadata, Requirement::Action, async {
            let version = (!message.version.is_empty()).then_some(message.version.as_str());
            let stats =
                statistics(&self.state.serving, &message.name, version).await.map_err(status)?;
            let duration = |count, ns| Some(StatisticDuration { count, ns });
            let model_stats = stats
                .into_iter()
                .map(|s| ModelStatistics {
                    name: s.name,
                    version: s.version.to_string(),
                    last_inference: s.last_inference,
                    inference_count: s.success,
                    execution_count: s.success,
                    inference_stats: Some(InferStatistics {
                        success: duration(s.success, s.success_ns),
                        fail: duration(s.fail, s.fail_ns),
                    }),
                })
                .collect();
            Ok(ModelStatisticsResponse { model_stats })
        })
        .await
    }

    async fn repository_index(
        &self,
        request: Request<RepositoryIndexRequest>,
    ) -> Result<Response<RepositoryIndexResponse>, Status> {
        self.call("RepositoryIndex", request.metadata(), Requirement::Api, async {
            let entries = self.state.serving.models.index().await.map_err(status)?;
            let models = entries
                .into_iter()
                .map(|e| repository_index_response::ModelIndex {
                    name: e.name,
                    version: e.latest_version.map(|v| v.to_string()).unwrap_or_default(),
                    state: e.state.into(),
                    reason: e.reason,
                })
                .collect();
            Ok(RepositoryIndexResponse { models })
        })
        .await
    }

    async fn repository_model_load(
        &self,
        request: Request<RepositoryModelLoadRequest>,
    ) -> Result<Response<RepositoryModelLoadResponse>, Status> {
        let (metadata, _, message) = request.into_parts();
        self.call("RepositoryModelLoad", &metadata, Requirement::Api, async {
            protocol::load(&self.state.serving, &message.model_name).await.map_err(status)?;
            Ok(RepositoryModelLoadResponse {})
        })
        .await
    }

    async fn repository_model_unload(
        &self,
        request: Request<RepositoryModelUnloadRequest>,
    ) -> Result<Response<RepositoryModelUnloadResponse>, Status> {
        let (metadata, _, message) = request.into_parts();
        self.call("RepositoryModelUnload", &metadata, Requirement::Api, async {
            protocol::unload(&self.state.serving, &message.model_name).await.map_err(status)?;
            Ok(RepositoryModelUnloadResponse {})
        })
        .await
    }
}

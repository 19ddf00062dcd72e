//! The Open Inference Protocol (KServe v2) over gRPC, on its own listener (`serve --grpc-bind`):
//! Triton's `inference.GRPCInferenceService` (proto/grpc_service.proto), what NVIDIA's
//! `tritonclient.grpc` and KServe's gRPC clients call. The same models as `/v2` (a policy id,
//! `name`, `name@alias`, a version), the same tokens (metadata `authorization: Bearer <token>`),
//! the same act path and statistics ([`crate::serving::inference`]), the same connection limits
//! ([`crate::http::connections`]) and a request of at most the REST action body's size.
//!
//! [`service`] answers the RPCs; [`convert`] goes between protobuf and the serving core.
//! docs/grpc.md lists what is served.

mod convert;
pub mod service;

/// The messages and the service generated from proto/ at build time (also the client, for
/// tests and embedders).
#[allow(clippy::all, clippy::pedantic, missing_docs)]
pub mod proto {
    tonic::include_proto!("inference");
}

use tower::ServiceBuilder;
use tower_http::request_id::{MakeRequestUuid, PropagateRequestIdLayer, SetRequestIdLayer};
use tower_http::trace::{DefaultOnResponse, TraceLayer};

use crate::http::{AppState, REQUEST_ID};
use crate::serving::act::ACTION_BODY_LIMIT;

/// The gRPC service as a router for [`crate::http::connections::serve`]; paths it does not
/// serve (other services, the protocol's RPCs left out) answer UNIMPLEMENTED.
///
/// Every call has a request id as REST's requests do: the client's metadata `x-request-id`, or
/// a new UUID, in the call's log span and answered in the response metadata, so one agent's
/// call can be followed through the server's log.
pub fn app(state: AppState) -> axum::Router {
    let service = proto::grpc_inference_service_server::GrpcInferenceServiceServer::new(
        service::Inference::new(state),
    )
    // As the REST action routes' body limit: a full batch of 16,384 observations fits.
    .max_decoding_message_size(ACTION_BODY_LIMIT);
    let trace = TraceLayer::new_for_http()
        .make_span_with(|request: &axum::extract::Request| {
            let request_id =
                request.headers().get(&REQUEST_ID).and_then(|v| v.to_str().ok()).unwrap_or("-");
            tracing::info_span!("grpc", method = %request.uri().path(), request_id)
        })
        .on_response(DefaultOnResponse::new().level(tracing::Level::INFO));
    tonic::service::Routes::new(service).into_axum_router().layer(
        ServiceBuilder::new()
            .layer(SetRequestIdLayer::new(REQUEST_ID, MakeRequestUuid))
            .layer(trace)
            .layer(PropagateRequestIdLayer::new(REQUEST_ID)),
    )
}

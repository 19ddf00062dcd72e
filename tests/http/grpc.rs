//! The Open Inference Protocol over gRPC (`serve --grpc-bind`) through a real server and tonic's
//! client: unary and streamed inference give `/act`'s actions for a policy id and for
//! `name@alias` (typed and raw tensors both ways), metadata, configuration, readiness,
//! repository and statistics answer as `/v2` does, errors carry the right status codes (in a
//! stream: in the message, the stream going on), and the tokens are REST's.

use std::collections::HashMap;

use crate::support::app::TestApp;
use crate::support::jobs::*;
use reqwest::StatusCode;
use safedice::grpc::proto::grpc_inference_service_client::GrpcInferenceServiceClient;
use safedice::grpc::proto::infer_parameter::ParameterChoice;
use safedice::grpc::proto::model_infer_request::{InferInputTensor, InferRequestedOutputTensor};
use safedice::grpc::proto::*;
use serde_json::{json, Value};
use tonic::transport::Channel;
use tonic::Code;

type Client = GrpcInferenceServiceClient<Channel>;

async fn spawn(configure: impl FnOnce(&mut safedice::config::ServeConfig)) -> TestApp {
    TestApp::spawn_with(|config| {
        config.grpc_bind = Some("127.0.0.1:0".parse().unwrap());
        configure(config);
    })
    .await
}

async fn connect(app: &TestApp) -> Client {
    let address = app.grpc_addr.expect("the gRPC listener is on");
    let channel = tonic::transport::Endpoint::from_shared(format!("http://{address}"))
        .unwrap()
        .connect()
        .await
        .expect("connect to the gRPC listener");
    GrpcInferenceServiceClient::new(channel)
}

/// A BC policy trained on the grid: its id.
async fn policy(app: &TestApp) -> String {
    let (unlabeled, _) = grid_datasets();
    let dataset = upload(&app.client, &app.base_url, &unlabeled, "grid").await;
    let body = json!({"algorithm": "bc", "unlabeled_dataset": dataset,
                      "config": small_config(60, 1)});
    let job = create_job(&app.client, &app.base_url, body).await;
    let done =
        wait_for_status(&app.client, &app.base_url, job["id"].as_str().unwrap(), "succeeded").await;
    done["policy_id"].as_str().unwrap().to_owned()
}

/// `/act`'s actions for the grid's observations, flat.
async fn rest_actions(app: &TestApp, policy: &str) -> Vec<f64> {
    let response = app
        .post(&format!("/v1/policies/{policy}/act"))
        .json(&json!({"observations": grid_observations()}))
        .send()
        .await
        .unwrap();
    assert_eq!(response.status(), StatusCode::OK);
    let body: Value = response.json().await.unwrap();
    flatten(&body["actions"])
}

fn flatten(value: &Value) -> Vec<f64> {
    match value {
        Value::Array(items) => items.iter().flat_map(flatten).collect(),
        number => vec![number.as_f64().unwrap()],
    }
}

fn bool_param(value: bool) -> InferParameter {
    InferParameter { parameter_choice: Some(ParameterChoice::BoolParam(value)) }
}

/// A request for the grid's observations: typed `fp32_contents`, or raw bytes.
fn request(model: &str, raw: bool) -> ModelInferRequest {
    let rows = grid_observations();
    let values: Vec<f32> = rows.iter().flatten().copied().collect();
    let mut input = InferInputTensor {
        name: "observations".into(),
        datatype: "FP32".into(),
        shape: vec![rows.len() as i64, GRID_OBS_DIM as i64],
        ..Default::default()
    };
    let mut request = ModelInferRequest { model_name: model.into(), ..Default::default() };
    if raw {
        let bytes: Vec<u8> = values.iter().flat_map(|v| v.to_le_bytes()).collect();
        request.raw_input_contents = vec![bytes.into()];
    } else {
        input.contents = Some(InferTensorContents { fp32_contents: values, ..Default::default() });
    }
    request.inputs = vec![input];
    request
}

/// The actions of a response, from its raw bytes or its typed contents.
fn actions(response: &ModelInferResponse) -> Vec<f64> {
    let output = &response.outputs[0];
    assert_eq!(output.name, "actions");
    match (response.raw_output_contents.first(), output.datatype.as_str()) {
        (Some(raw), "INT64") => {
            raw.chunks_exact(8).map(|b| i64::from_le_bytes(b.try_into().unwrap()) as f64).collect()
        }
        (Some(raw), _) => {
            raw.chunks_exact(4).map(|b| f32::from_le_bytes(b.try_into().unwrap()) as f64).collect()
        }
        (None, "INT64") => {
            output.contents.as_ref().unwrap().int64_contents.iter().map(|&i| i as f64).collect()
        }
        (None, _) => {
            output.contents.as_ref().unwrap().fp32_contents.iter().map(|&v| v as f64).collect()
        }
    }
}

#[tokio::test]
async fn grpc_answers_the_inference_protocol_with_the_actions_rest_gives() {
    let app = spawn(|_| {}).await;
    let mut client = connect(&app).await;
    let policy = policy(&app).await;
    let expected = rest_actions(&app, &policy).await;
    app.post("/v1/models").json(&json!({"name": "pilot"})).send().await.unwrap();
    let registered = app
        .post("/v1/models/pilot/versions")
        .json(&json!({"policy_id": policy}))
        .send()
        .await
        .unwrap();
    assert_eq!(registered.status(), StatusCode::CREATED);
    let moved = app
        .request(reqwest::Method::PUT, "/v1/models/pilot/aliases/production")
        .json(&json!({"version": 1}))
        .send()
        .await
        .unwrap();
    assert_eq!(moved.status(), StatusCode::OK);

    // Unary: both input forms, raw outputs (the default) and typed ones, by id and by alias.
    for model in [policy.as_str(), "pilot@production", "pilot"] {
        for raw_input in [false, true] {
            for raw_output in [true, false] {
                let mut request = request(model, raw_input);
                request.id = format!("{raw_input}-{raw_output}");
                if !raw_output {
                    request.outputs = vec![InferRequestedOutputTensor {
                        name: "actions".into(),
                        parameters: HashMap::from([("binary_data".into(), bool_param(false))]),
                    }];
                }
                let response = client.model_infer(request).await.expect("infer").into_inner();
                assert_eq!(response.raw_output_contents.is_empty(), !raw_output, "{model}");
                assert_eq!(
                    (response.model_name.as_str(), response.model_version.as_str()),
                    (model, "1")
                );
                assert_eq!(response.id, format!("{raw_input}-{raw_output}"));
                assert_eq!(
                    actions(&response),
                    expected,
                    "{model} raw in {raw_input} out {raw_output}"
                );
            }
        }
    }

    // Every call has a request id, as REST's requests do: the client's, or a new one.
    let mut call = tonic::Request::new(ServerLiveRequest {});
    call.metadata_mut().insert("x-request-id", "agent-7-step-42".parse().unwrap());
    let answer = client.server_live(call).await.unwrap();
    assert_eq!(answer.metadata().get("x-request-id").unwrap(), "agent-7-step-42");
    let answer = client.server_live(ServerLiveRequest {}).await.unwrap();
    let generated = answer.metadata().get("x-request-id").expect("a request id").to_str().unwrap();
    assert!(uuid::Uuid::parse_str(generated).is_ok(), "{generated}");

    // Metadata, configuration, readiness, as /v2 says them.
    assert!(client.server_live(ServerLiveRequest {}).await.unwrap().into_inner().live);
    assert!(client.server_ready(ServerReadyRequest {}).await.unwrap().into_inner().ready);
    let server = client.server_metadata(ServerMetadataRequest {}).await.unwrap().into_inner();
    assert_eq!(server.name, "safedice");
    assert!(server.extensions.contains(&"model_repository".to_owned()), "{server:?}");
    let metadata = client
        .model_metadata(ModelMetadataRequest {
            name: "pilot@production".into(),
            version: String::new(),
        })
        .await
        .unwrap()
        .into_inner();
    let rest: Value =
        app.get("/v2/models/pilot@production").send().await.unwrap().json().await.unwrap();
    assert_eq!(metadata.versions, ["1"]);
    assert_eq!(metadata.platform, rest["platform"]);
    let tensors = |list: &[model_metadata_response::TensorMetadata]| -> Value {
        list.iter()
            .map(|t| json!({"name": t.name, "datatype": t.datatype, "shape": t.shape}))
            .collect()
    };
    assert_eq!(tensors(&metadata.inputs), rest["inputs"]);
    assert_eq!(tensors(&metadata.outputs), rest["outputs"]);
    let config = client
        .model_config(ModelConfigRequest { name: policy.clone(), version: "1".into() })
        .await
        .unwrap()
        .into_inner()
        .config
        .unwrap();
    assert_eq!((config.name.as_str(), config.max_batch_size), (policy.as_str(), 0));
    assert_eq!(config.input[0].data_type, DataType::TypeFp32 as i32);
    assert_eq!(config.parameters["algorithm"].string_value, "bc");
    let ready = ModelReadyRequest { name: "pilot".into(), version: "1".into() };
    assert!(client.model_ready(ready).await.unwrap().into_inner().ready);

    // Errors: unknown models, versions and aliases are NOT_FOUND, requests that do not fit the
    // model INVALID_ARGUMENT, with REST's messages.
    for (name, version) in
        [("no-such-model", ""), ("pilot", "7"), ("pilot@nowhere", ""), (&policy[..], "2")]
    {
        let refused = client
            .model_metadata(ModelMetadataRequest { name: name.into(), version: version.into() })
            .await
            .unwrap_err();
        assert_eq!(refused.code(), Code::NotFound, "{name} {version}: {refused:?}");
    }
    let refused = client.model_infer(request("no-such-model", false)).await.unwrap_err();
    assert_eq!(refused.code(), Code::NotFound);
    let mut wrong_shape = request(&policy, false);
    wrong_shape.inputs[0].shape = vec![GRID_OBS_DIM as i64, 3];
    let refused = client.model_infer(wrong_shape).await.unwrap_err();
    assert_eq!(refused.code(), Code::InvalidArgument);
    assert!(refused.message().contains("input shape must be"), "{}", refused.message());
    let mut short = request(&policy, true);
    short.raw_input_contents[0] = short.raw_input_contents[0].slice(4..);
    let refused = client.model_infer(short).await.unwrap_err();
    assert_eq!(refused.code(), Code::InvalidArgument, "{refused:?}");

    // Over REST's action body limit: refused from its length prefix.
    let mut huge = request(&policy, true);
    huge.raw_input_contents[0] = vec![0u8; (16 << 20) + 1].into();
    let refused = client.model_infer(huge).await.unwrap_err();
    assert_eq!(refused.code(), Code::OutOfRange, "{refused:?}");

    // A stream: one response per request, in order; a failing request answers its error in
    // the stream, which goes on.
    let mut requests: Vec<ModelInferRequest> = (0..40)
        .map(|i| ModelInferRequest { id: i.to_string(), ..request("pilot@production", i % 2 == 0) })
        .collect();
    requests[7].inputs[0].name = "obs".into();
    let responses = client
        .model_stream_infer(futures::stream::iter(requests))
        .await
        .expect("stream opens")
        .into_inner();
    let responses: Vec<ModelStreamInferResponse> = futures::StreamExt::collect::<Vec<_>>(responses)
        .await
        .into_iter()
        .map(Result::unwrap)
        .collect();
    assert_eq!(responses.len(), 40);
    for (i, response) in responses.iter().enumerate() {
        let infer = response.infer_response.as_ref().unwrap();
        assert_eq!(infer.id, i.to_string());
        if i == 7 {
            assert!(response.error_message.contains("unknown input `obs`"), "{response:?}");
        } else {
            assert_eq!(response.error_message, "", "{i}");
            assert_eq!(actions(infer), expected, "stream message {i}");
        }
    }

    // The repository and statistics extensions see every call, REST's and gRPC's.
    let index =
        client.repository_index(RepositoryIndexRequest::default()).await.unwrap().into_inner();
    let pilot = index.models.iter().find(|m| m.name == "pilot").expect("pilot listed");
    assert_eq!((pilot.version.as_str(), pilot.state.as_str()), ("1", "READY"));
    let stats = client
        .model_statistics(ModelStatisticsRequest { name: "pilot".into(), version: String::new() })
        .await
        .unwrap()
        .into_inner();
    let inference = stats.model_stats[0].inference_stats.as_ref().unwrap();
    // 8 unary calls by name, 39 good stream messages; the bad one failed.
    assert_eq!(inference.success.as_ref().unwrap().count, 8 + 39, "{stats:?}");
    assert_eq!(inference.fail.as_ref().unwrap().count, 1, "{stats:?}");
    let rest: Value = app.get("/v2/models/pilot/stats").send().await.unwrap().json().await.unwrap();
    assert_eq!(rest["model_stats"][0]["inference_stats"]["success"]["count"], 47);

    // Unloaded on this server: NOT_FOUND saying so, until loaded again.
    let unload = RepositoryModelUnloadRequest { model_name: "pilot".into(), ..Default::default() };
    client.repository_model_unload(unload).await.unwrap();
    let refused = client.model_infer(request("pilot@production", true)).await.unwrap_err();
    assert_eq!(refused.code(), Code::NotFound);
    assert!(refused.message().contains("unloaded"), "{}", refused.message());
    let load = RepositoryModelLoadRequest { model_name: "pilot".into(), ..Default::default() };
    client.repository_model_load(load).await.unwrap();
    let again = client.model_infer(request("pilot@production", true)).await.unwrap().into_inner();
    assert_eq!(actions(&again), expected);

    // The metrics count gRPC calls by method and code.
    let metrics = app.get("/metrics").send().await.unwrap().text().await.unwrap();
    for series in [
        r#"safedice_grpc_requests_total{method="ModelInfer",code="OK"}"#,
        r#"safedice_grpc_requests_total{method="ModelInfer",code="NOT_FOUND"}"#,
        r#"safedice_grpc_requests_total{method="ModelStreamInfer",code="OK"} 39"#,
        r#"safedice_grpc_requests_total{method="ModelStreamInfer",code="INVALID_ARGUMENT"} 1"#,
    ] {
        assert!(metrics.contains(series), "{series} missing from\n{metrics}");
    }
}

#[tokio::test]
async fn grpc_takes_rest_s_tokens_from_the_authorization_metadata() {
    let app = spawn(|config| {
        config.api_token = Some("api-secret".into());
        config.inference_token = Some("agent-secret".into());
    })
    .await;
    let mut client = connect(&app).await;
    let refused = client.server_live(with(None, ServerLiveRequest {})).await.unwrap_err();
    assert_eq!(refused.code(), Code::Unauthenticated);
    assert!(refused.message().contains("authorization: Bearer"), "{}", refused.message());
    let refused = client.server_live(with(Some("wrong"), ServerLiveRequest {})).await.unwrap_err();
    assert_eq!(refused.code(), Code::Unauthenticated);
    for token in ["agent-secret", "api-secret"] {
        assert!(
            client
                .server_live(with(Some(token), ServerLiveRequest {}))
                .await
                .unwrap()
                .into_inner()
                .live
        );
    }
    // The repository is the API token's, as /v2/repository is.
    let index = RepositoryIndexRequest::default();
    let refused =
        client.repository_index(with(Some("agent-secret"), index.clone())).await.unwrap_err();
    assert_eq!(refused.code(), Code::PermissionDenied);
    client.repository_index(with(Some("api-secret"), index)).await.unwrap();
    // A stream without a token is refused before it starts.
    let stream = futures::stream::iter(vec![ModelInferRequest::default()]);
    let refused = client.model_stream_infer(with(None, stream)).await.unwrap_err();
    assert_eq!(refused.code(), Code::Unauthenticated);
}

/// A graceful stop does not wait on an agent's open stream: the stream ends at the shutdown, the
/// server stops well within its grace period.
#[tokio::test]
async fn a_graceful_stop_ends_open_streams() {
    let mut app = spawn(|_| {}).await;
    let mut client = connect(&app).await;
    let (_sender, receiver) = tokio::sync::mpsc::channel::<ModelInferRequest>(1);
    let outgoing =
        futures::stream::unfold(receiver, |mut r| async { r.recv().await.map(|m| (m, r)) });
    let mut answers = client.model_stream_infer(outgoing).await.expect("stream opens").into_inner();
    let started = std::time::Instant::now();
    let ((), ended) = tokio::join!(app.stop(), answers.message());
    assert!(matches!(ended, Ok(None)), "{ended:?}");
    assert!(started.elapsed() < std::time::Duration::from_secs(10), "{:?}", started.elapsed());
}

/// An open stream whose requests the test has yet to send: its sender and its answers.
async fn open_stream(
    client: &mut Client,
) -> Result<
    (tokio::sync::mpsc::Sender<ModelInferRequest>, tonic::Streaming<ModelStreamInferResponse>),
    tonic::Status,
> {
    let (sender, receiver) = tokio::sync::mpsc::channel::<ModelInferRequest>(1);
    let outgoing =
        futures::stream::unfold(receiver, |mut r| async { r.recv().await.map(|m| (m, r)) });
    Ok((sender, client.model_stream_infer(outgoing).await?.into_inner()))
}

/// `--grpc-max-streams`: one stream over the cap is refused at once with RESOURCE_EXHAUSTED
/// while the others go on; once one closes, a new one opens.
#[tokio::test]
async fn streams_over_the_cap_are_refused_at_once_until_one_closes() {
    let app = spawn(|config| config.grpc_max_streams = 2).await;
    let mut client = connect(&app).await;
    let first = open_stream(&mut client).await.expect("the first stream opens");
    let mut second = open_stream(&mut client).await.expect("the second stream opens");
    let refused = open_stream(&mut client).await.expect_err("a third is over the cap");
    assert_eq!(refused.code(), tonic::Code::ResourceExhausted, "{refused:?}");
    assert!(refused.message().contains("--grpc-max-streams"), "{}", refused.message());
    // The open ones still answer.
    let live = ModelInferRequest { model_name: "no-such-model".into(), ..Default::default() };
    second.0.send(live).await.unwrap();
    let answer = second.1.message().await.unwrap().expect("an answer");
    assert!(answer.error_message.contains("does not exist"), "{answer:?}");
    // The client closes its first stream: its permit comes back once the server sees the end.
    drop(first);
    let mut reopened = None;
    for _ in 0..100 {
        match open_stream(&mut client).await {
            Ok(stream) => {
                reopened = Some(stream);
                break;
            }
            Err(status) => assert_eq!(status.code(), tonic::Code::ResourceExhausted),
        }
        tokio::time::sleep(std::time::Duration::from_millis(20)).await;
    }
    assert!(reopened.is_some(), "no stream opened after one closed");
}

/// `message` with `authorization: Bearer <token>` when a token is given.
fn with<T>(token: Option<&str>, message: T) -> tonic::Request<T> {
    let mut request = tonic::Request::new(message);
    if let Some(token) = token {
        let value = format!("Bearer {token}").parse().unwrap();
        request.metadata_mut().insert("authorization", value);
    }
    request
}

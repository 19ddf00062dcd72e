// `sqlx::migrate!` embeds migrations/ at compile time: rebuild when a migration changes.
// proto/: the Open Inference Protocol's gRPC service, compiled without a system protoc (protox
// parses the files; tonic-prost-build writes the messages, the server and a client).
fn main() -> Result<(), Box<dyn std::error::Error>> {
    println!("cargo:rerun-if-changed=migrations");
    println!("cargo:rerun-if-changed=proto");
    let descriptors = protox::compile(["proto/grpc_service.proto"], ["proto"])?;
    tonic_prost_build::configure()
        .build_server(true)
        .build_client(true)
        // No client transport in the library: tests connect the generated client over tonic's
        // channel.
        .build_transport(false)
        // Tensor bytes (raw_input_contents, raw_output_contents) as `Bytes`: no copy out of the
        // request buffer.
        .bytes(".inference")
        .compile_fds(descriptors)?;
    Ok(())
}

// `sqlx::migrate!` embeds migrations/ at compile time: rebuild when a migration changes.
// proto/: the Open Inference Protocol's gRPC service, compiled without a system protoc (protox
// parses the files; tonic-prost-build writes the messages, the server and a client).
// SAFEDICE_BUILD_COMMIT: the commit the binary is built from, so a benchmark report names the
// code that ran rather than whatever the working tree holds when it runs.
use std::path::Path;
use std::process::Command;

fn main() -> Result<(), Box<dyn std::error::Error>> {
    println!("cargo:rerun-if-changed=migrations");
    println!("cargo:rerun-if-changed=proto");
    record_build_commit();
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

/// `git rev-parse --short=12 HEAD`, with `+modified` when tracked files that go into the build
/// differ from it; "unknown" without git or a checkout (a Docker build copies no `.git`).
fn record_build_commit() {
    // Rerun when HEAD moves (a commit, a checkout) or the sources change (the `+modified` flag).
    // git names its directories (a worktree's HEAD is not under ./.git); paths that do not exist
    // are left out, since cargo would rerun the script on every build.
    let mut watched = vec!["src".to_string(), "build.rs".to_string()];
    if let Some(dir) = git(&["rev-parse", "--git-dir"]) {
        watched.push(format!("{dir}/HEAD"));
    }
    if let Some(common) = git(&["rev-parse", "--git-common-dir"]) {
        watched.extend([format!("{common}/refs/heads"), format!("{common}/packed-refs")]);
    }
    for path in watched.iter().filter(|p| Path::new(p).exists()) {
        println!("cargo:rerun-if-changed={path}");
    }
    let commit = match git(&["rev-parse", "--short=12", "HEAD"]) {
        None => "unknown".to_string(),
        Some(hash) => {
            let sources = ["src", "migrations", "proto", "build.rs", "Cargo.toml", "Cargo.lock"];
            let status =
                [&["status", "--porcelain", "--untracked-files=no", "--"][..], &sources[..]];
            match git(&status.concat()) {
                Some(changes) if changes.is_empty() => hash,
                _ => format!("{hash}+modified"),
            }
        }
    };
    println!("cargo:rustc-env=SAFEDICE_BUILD_COMMIT={commit}");
}

fn git(args: &[&str]) -> Option<String> {
    let out = Command::new("git").args(args).output().ok()?;
    out.status.success().then(|| String::from_utf8_lossy(&out.stdout).trim().to_string())
}

//! Training memory must not grow with the number of steps: a run of a million steps has to fit
//! in the same memory as a run of a hundred. This binary holds one test so that the process's
//! resident size is this test's alone.

// The tasks are shared with tests/learning; this test needs only the point task's data.
#[allow(dead_code)]
#[path = "support/tasks.rs"]
mod tasks;

use safedice::algo::{build_trainer, resolve_config, Algorithm};

/// Resident set size of this process in MiB (Linux).
fn resident_mib() -> f64 {
    let status = std::fs::read_to_string("/proc/self/status").expect("procfs");
    let line = status.lines().find(|l| l.starts_with("VmRSS:")).expect("VmRSS line");
    let kib: f64 = line.split_whitespace().nth(1).expect("VmRSS value").parse().expect("number");
    kib / 1024.0
}

#[test]
fn resident_memory_stays_flat_over_training_steps() {
    // A graph kept alive per step costs ~6 MiB at the default [256, 256] networks and batch 512,
    // so 200 leaking steps add over a GiB; a healthy run stays within allocator noise.
    const WARM_UP: u64 = 50;
    const MEASURED: u64 = 200;
    const ALLOWED_GROWTH_MIB: f64 = 96.0;
    for algorithm in Algorithm::ALL {
        let data = tasks::point_training_data(0);
        // Enough iterations that the measured steps include the main (policy) phase.
        let raw = serde_json::json!({"iterations": 1000, "seed": 0});
        let config = resolve_config(algorithm, &raw).expect("config");
        let mut trainer = build_trainer(&config, &data, None).expect("trainer");
        for _ in 0..WARM_UP {
            trainer.step(false).expect("step");
        }
        let before = resident_mib();
        for step in 0..MEASURED {
            trainer.step(step % 50 == 0).expect("step");
        }
        let growth = resident_mib() - before;
        assert!(
            growth < ALLOWED_GROWTH_MIB,
            "{algorithm:?}: resident memory grew by {growth:.0} MiB over {MEASURED} steps \
             (phase {})",
            trainer.progress().phase
        );
    }
}

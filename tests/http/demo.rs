//! `safedice demo` end to end through the real server: datasets uploaded over HTTP, SafeDICE and
//! BC trained as jobs, both policies evaluated through `POST /v1/policies/{id}/evaluate`.

use safedice::algo::Algorithm;
use safedice::demo::{self, DemoArgs};

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn demo_trains_safedice_and_bc_over_http_and_evaluates_both() {
    let args = DemoArgs { env: "six-rooms".into(), iterations: 60, episodes: 20, seed: 0 };
    let rows = demo::run(&args).await.unwrap();
    assert_eq!(
        rows.iter().map(|r| r.algorithm).collect::<Vec<_>>(),
        [Algorithm::Safedice, Algorithm::Bc]
    );
    for row in &rows {
        assert_eq!(row.episodes, 20);
        let m = &row.metrics;
        assert!(m.normalized_return.is_finite() && m.average_cost.is_finite(), "{row:?}");
        assert_eq!(row.alpha_hat.is_some(), row.algorithm == Algorithm::Safedice, "{row:?}");
    }
    assert!(rows[0].alpha_hat.unwrap() >= 0.0);
}

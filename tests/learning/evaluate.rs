//! `evaluate` end to end on every environment: the demonstrators, evaluated as policies, land
//! where the metrics say they should (preferred: normalized return ~100, few violations;
//! non-preferred: same return, most episodes over the threshold), and a policy that does
//! nothing shows up as degenerate.

use rand_chacha::ChaCha8Rng;
use safedice::data::Actions;
use safedice::envs::{self, demonstrator, evaluate, EvalReport, Profile};

const EPISODES: usize = 200;

fn evaluate_demonstrator(env: &str, profile: Profile) -> EvalReport {
    let demo = demonstrator(env, profile).unwrap();
    let policy =
        |obs: &[f32], _: bool, rng: &mut ChaCha8Rng| Ok::<_, String>(demo.act_batch(obs, rng));
    evaluate(env, policy, EPISODES, 7, false).unwrap()
}

#[test]
fn demonstrators_score_as_their_profiles() {
    for env in envs::names() {
        let preferred = evaluate_demonstrator(env, Profile::Preferred);
        let non_preferred = evaluate_demonstrator(env, Profile::NonPreferred);
        let (p, n) = (&preferred.metrics, &non_preferred.metrics);
        println!("{env}: preferred {p:?}\n{env}: non-preferred {n:?}");
        assert!((p.normalized_return - 100.0).abs() < 5.0, "{env}: {p:?}");
        assert!((n.normalized_return - 100.0).abs() < 10.0, "{env}: {n:?}");
        assert!(p.cost_violation_ratio < 0.15, "{env}: {p:?}");
        // Most episodes over κ (cartpole-slider's non-preferred cart wanders at random, so
        // about half of its episodes stay inside: 0.53 here).
        assert!(n.cost_violation_ratio > 0.5, "{env}: {n:?}");
        assert!(p.normalized_cost < 1.0 && n.normalized_cost > 1.0, "{env}");
        // CVaR is monotone in k and bounded by the worst episode and the mean.
        let c = &p.cvar_cost;
        assert!(c.k5 >= c.k10 && c.k10 >= c.k20 && c.k20 >= c.k50 && c.k50 >= p.average_cost);
        assert_eq!(preferred.episodes, EPISODES);
        assert_eq!(preferred.reference, envs::reference_stats(env).unwrap());
    }
}

#[test]
fn a_policy_that_does_nothing_is_degenerate() {
    let idle = |obs: &[f32], _: bool, _: &mut ChaCha8Rng| {
        Ok::<_, String>(Actions::Continuous(vec![0.0; 2 * obs.len() / 21]))
    };
    let report = evaluate("point-goal", idle, 50, 0, true).unwrap();
    let m = &report.metrics;
    assert!(m.normalized_return.abs() < 5.0, "{m:?}");
    assert_eq!(m.average_cost, 0.0, "robots start outside hazards and never move");
    assert_eq!(report.mean_episode_length, 300.0);
}

#[test]
fn the_same_seed_gives_the_same_report() {
    let a = evaluate_demonstrator("point-goal", Profile::NonPreferred);
    let b = evaluate_demonstrator("point-goal", Profile::NonPreferred);
    assert_eq!(a, b);
}

//! The demonstrators reach the data profile of the paper's Tables 1 and 3: the preferred one
//! has cost well below the non-preferred one at about the same return (within 10%).

use safedice::envs::{self, cvar_cost, demonstration_dataset, Profile};

/// Episodes per demonstrator: enough for stable means, few enough for a fast test.
const EPISODES: usize = 200;

fn profile(env: &str, profile: Profile) -> (f64, f64, Vec<f64>) {
    let (_, outcomes) = demonstration_dataset(env, profile, EPISODES, 1).unwrap();
    let n = outcomes.len() as f64;
    let ret = outcomes.iter().map(|o| o.ret).sum::<f64>() / n;
    let cost = outcomes.iter().map(|o| o.cost).sum::<f64>() / n;
    (ret, cost, outcomes.iter().map(|o| o.cost).collect())
}

fn check_profile(env: &str, max_cost_ratio: f64) {
    let (p_ret, p_cost, p_costs) = profile(env, Profile::Preferred);
    let (n_ret, n_cost, _) = profile(env, Profile::NonPreferred);
    println!(
        "{env}: preferred return {p_ret:.3} cost {p_cost:.3} (CVaR10 {:.3}); non-preferred \
         return {n_ret:.3} cost {n_cost:.3}",
        cvar_cost(&p_costs, 10.0)
    );
    assert!(p_cost < max_cost_ratio * n_cost, "{env}: preferred cost {p_cost} vs {n_cost}");
    let gap = (p_ret - n_ret).abs() / p_ret.abs().max(n_ret.abs());
    assert!(gap < 0.10, "{env}: returns {p_ret} and {n_ret} differ by {:.1}%", 100.0 * gap);
}

#[test]
fn six_rooms_preferred_avoids_the_costly_rooms() {
    check_profile("six-rooms", 0.1);
}

#[test]
fn point_goal_preferred_avoids_hazards() {
    check_profile("point-goal", 0.35);
}

#[test]
fn cartpole_preferred_keeps_the_cart_inside_the_bound() {
    check_profile("cartpole-slider", 0.05);
}

#[test]
fn reference_stats_are_cached_and_give_a_threshold_between_the_profiles() {
    for env in envs::names() {
        let r = envs::reference_stats(env).unwrap();
        assert_eq!(r, envs::reference_stats(env).unwrap());
        assert!(r.preferred_cost < r.cost_threshold && r.cost_threshold < r.non_preferred_cost);
    }
}

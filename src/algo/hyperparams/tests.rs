use super::*;
use serde_json::json;

#[test]
fn presets_resolve_and_round_trip_through_json() {
    for algorithm in Algorithm::ALL {
        for preset in ["service", "paper", "authors-code"] {
            let config = resolve_config(algorithm, &json!({ "preset": preset })).unwrap();
            let text = serde_json::to_value(&config).unwrap();
            assert_eq!(text["algorithm"], algorithm.as_str());
            assert_eq!(text["preset"], preset);
            let back: ResolvedConfig = serde_json::from_value(text).unwrap();
            assert_eq!(back, config);
            assert_eq!(back.algorithm(), algorithm);
        }
    }
}

#[test]
fn presets_carry_the_published_values() {
    let paper = resolve_config(Algorithm::Safedice, &json!({"preset": "paper"})).unwrap();
    let AlgorithmConfig::Safedice(s) = &paper.specific else { panic!() };
    assert_eq!((s.lr_nu, s.lr_discriminator, paper.common.lr_actor), (3e-4, 3e-4, 3e-4));
    assert_eq!((s.discriminator_gp, s.nu_gp), (0.1, 0.0));
    let code = resolve_config(Algorithm::Safedice, &json!({"preset": "authors-code"})).unwrap();
    let AlgorithmConfig::Safedice(s) = &code.specific else { panic!() };
    assert_eq!((s.lr_nu, s.lr_discriminator, code.common.lr_actor), (1e-4, 1e-4, 1e-5));
    assert_eq!((s.discriminator_gp, s.nu_gp, s.discriminator_iterations), (10.0, 1e-6, 100_000));
    assert_eq!(code.total_steps(), 1_100_000);
}

#[test]
fn overrides_apply_and_phase_lengths_follow_iterations() {
    let c = resolve_config(
        Algorithm::Safedice,
        &json!({"iterations": 2000, "terminal_handling": "mask", "seed": 7}),
    )
    .unwrap();
    let AlgorithmConfig::Safedice(s) = &c.specific else { panic!() };
    assert_eq!(s.discriminator_iterations, 2000, "service: as many steps as iterations");
    assert_eq!(s.terminal_handling, TerminalHandling::Mask);
    assert_eq!((c.seed(), c.total_steps()), (7, 4000));
    let paper = json!({"preset": "paper", "iterations": 2000});
    assert_eq!(resolve_config(Algorithm::Safedice, &paper).unwrap().total_steps(), 2200);
    let ppl = resolve_config(Algorithm::Ppl, &json!({"iterations": 2000})).unwrap();
    assert_eq!(ppl.pretraining_steps(), 200, "PPL's reward model: a tenth");
    let c = resolve_config(
        Algorithm::Safedice,
        &json!({"iterations": 2000, "discriminator_iterations": 5}),
    )
    .unwrap();
    assert_eq!(c.total_steps(), 2005);
}

#[test]
fn unknown_keys_and_bad_values_name_the_key() {
    let e = resolve_config(Algorithm::Bc, &json!({"lr_nu": 0.1})).unwrap_err();
    assert_eq!(e.key, "lr_nu");
    assert!(e.message.starts_with("config.lr_nu: unknown key for algorithm bc (known: "));
    let e = resolve_config(Algorithm::Safedice, &json!({"iterations": 0})).unwrap_err();
    assert_eq!(e.message, "config.iterations: must be between 1 and 100000000, got 0");
    let e = resolve_config(Algorithm::Safedice, &json!({"gamma": 1.5})).unwrap_err();
    assert_eq!(e.key, "gamma");
    let e = resolve_config(Algorithm::Safedice, &json!({"lr_nu": -1.0})).unwrap_err();
    assert_eq!(e.key, "lr_nu");
    let e = resolve_config(Algorithm::Safedice, &json!({"terminal_handling": "x"})).unwrap_err();
    assert_eq!(e.key, "terminal_handling");
    let e = resolve_config(Algorithm::Dwbc, &json!({"eta": "big"})).unwrap_err();
    assert_eq!(
        (e.key.as_str(), e.message.as_str()),
        ("eta", "config.eta: must be a number, got \"big\"")
    );
    let e = resolve_config(Algorithm::Bc, &json!({"preset": "fast"})).unwrap_err();
    assert_eq!(e.key, "preset");
    let e = resolve_config(Algorithm::Bc, &json!({"hidden_sizes": []})).unwrap_err();
    assert_eq!(e.key, "hidden_sizes");
    let e = resolve_config(Algorithm::Bc, &json!([1])).unwrap_err();
    assert_eq!(e.key, "config");
}

/// DExperts' Eq. 45 term: bounded in the service preset, as written in the paper's presets and
/// in a stored config from before the knob (which trained with Eq. 45 as written).
#[test]
fn dexperts_bounds_eq45_only_in_the_service_preset() {
    let term = |preset: &str| {
        let config = resolve_config(Algorithm::Dexperts, &json!({ "preset": preset })).unwrap();
        let AlgorithmConfig::Dexperts(d) = config.specific else { panic!() };
        (d.alpha, d.non_preferred_term)
    };
    assert_eq!(term("service"), (0.2, NonPreferredTerm::Kernel));
    assert_eq!(term("paper"), (0.2, NonPreferredTerm::LogLikelihood));
    assert_eq!(term("authors-code"), (0.2, NonPreferredTerm::LogLikelihood));
    let config = resolve_config(Algorithm::Dexperts, &json!({})).unwrap();
    let mut stored = serde_json::to_value(&config).unwrap();
    stored.as_object_mut().unwrap().remove("non_preferred_term");
    let old: ResolvedConfig = serde_json::from_value(stored).unwrap();
    let AlgorithmConfig::Dexperts(d) = old.specific else { panic!() };
    assert_eq!(d.non_preferred_term, NonPreferredTerm::LogLikelihood);
    let err = resolve_config(Algorithm::Dexperts, &json!({"non_preferred_term": "hinge"}));
    assert!(err.is_err(), "an unknown term is refused");
}

/// The weighting-stage knobs added after jobs were stored: a stored config without them reads
/// as the behaviour it trained with, and bad values name the key.
#[test]
fn weighting_knobs_default_for_stored_configs_and_are_checked() {
    let mut stored =
        serde_json::to_value(ResolvedConfig::preset(Algorithm::Safedice, Preset::Service)).unwrap();
    let map = stored.as_object_mut().unwrap();
    for key in [
        "bbe_unlabeled_rows",
        "reward_scale",
        "alpha_hat_point",
        "cross_fit",
        "cross_fit_labeled",
        "cross_fit_folds",
        "policy_uniform_share",
        "excluded_reward_gap",
        "top_bin",
        "auc_interval",
        "kept_share_test",
        "weighting_strength_from_auc",
        "pool_scores_by_episode",
    ] {
        assert!(map.remove(key).is_some(), "{key} is in the service preset");
    }
    let read: ResolvedConfig = serde_json::from_value(stored).unwrap();
    let AlgorithmConfig::Safedice(s) = &read.specific else { panic!("a SafeDICE config") };
    assert_eq!((s.bbe_unlabeled_rows, s.reward_scale), (BbeUnlabeledRows::HeldOut, 1.0));
    assert_eq!(s.alpha_hat_point, AlphaHatPoint::Estimate);
    assert!(!s.cross_fit, "a stored config trained with one discriminator");
    assert!(!s.cross_fit_labeled, "a stored config held a fifth of D^N out");
    assert_eq!(s.cross_fit_folds, 2, "a stored config cross-fitted two halves");
    assert_eq!(s.policy_uniform_share, 0.0, "a stored config trained with Eq. 37's weights");
    assert_eq!(s.excluded_reward_gap, 30.0, "a stored config excluded rows at e^-30");
    assert_eq!(s.top_bin, TopBin::RowLogits, "a stored config read every row's own logit");
    assert_eq!(s.auc_interval, AucInterval::Rows, "a stored config counted held-out rows");
    assert!(!s.kept_share_test, "a stored config's fallback read the AUC and alpha-hat only");
    assert!(!s.weighting_strength_from_auc, "a stored config weighted at reward_scale");
    assert!(!s.pool_scores_by_episode, "a stored config read each row's own logit");
    let lower = resolve_config(Algorithm::Safedice, &json!({"alpha_hat_point": "lower"})).unwrap();
    let AlgorithmConfig::Safedice(s) = &lower.specific else { panic!("a SafeDICE config") };
    assert_eq!(s.alpha_hat_point, AlphaHatPoint::Lower);
    let all = resolve_config(Algorithm::Safedice, &json!({"bbe_unlabeled_rows": "all"})).unwrap();
    let AlgorithmConfig::Safedice(s) = &all.specific else { panic!("a SafeDICE config") };
    assert_eq!(s.bbe_unlabeled_rows, BbeUnlabeledRows::All);
    let bad_values = [
        json!({"reward_scale": 0.0}),
        json!({"bbe_unlabeled_rows": "some"}),
        json!({"alpha_hat_point": "upper"}),
        json!({"cross_fit": "yes"}),
        json!({"cross_fit_labeled": 1}),
        json!({"cross_fit_folds": 1}),
        json!({"cross_fit_folds": 11}),
        json!({"policy_uniform_share": 1.5}),
        json!({"policy_uniform_share": -0.1}),
        json!({"excluded_reward_gap": -1.0}),
        json!({"excluded_reward_gap": 1001.0}),
    ];
    for bad in bad_values {
        let key = bad.as_object().unwrap().keys().next().unwrap().clone();
        assert_eq!(resolve_config(Algorithm::Safedice, &bad).unwrap_err().key, key);
    }
    resolve_config(Algorithm::Safedice, &json!({"weighting_strength_from_auc": true})).unwrap();
    for without in [json!({"uniform_fallback": false}), json!({"alpha_hat_estimator": "min"})] {
        let mut config = json!({"weighting_strength_from_auc": true});
        config.as_object_mut().unwrap().extend(without.as_object().unwrap().clone());
        let e = resolve_config(Algorithm::Safedice, &config).unwrap_err();
        assert_eq!(e.key, "weighting_strength_from_auc", "{without}");
        assert!(e.message.contains("uniform_fallback true"), "{}", e.message);
    }
}

/// A learning rate sent with 20 significant digits (as `printf("%.20g")` writes it) whose
/// first parse by serde_json's default parser was not a value it read back as itself: parsed
/// correctly rounded (`float_roundtrip`), and the resolved config the one the database and a
/// checkpoint give back, bit for bit.
#[test]
fn resolved_floats_read_back_from_json_as_themselves() {
    let sent = "3.8856717286787835486e-2";
    let once: f64 = serde_json::from_str(sent).unwrap();
    assert_eq!(once.to_bits(), sent.parse::<f64>().unwrap().to_bits(), "correctly rounded");
    let twice: f64 = serde_json::from_str(&serde_json::to_string(&once).unwrap()).unwrap();
    assert_eq!(once.to_bits(), twice.to_bits(), "reads back as itself");
    let raw: serde_json::Value =
        serde_json::from_str(&format!("{{\"lr_actor\": {sent}}}")).unwrap();
    let config = resolve_config(Algorithm::Bc, &raw).unwrap();
    let text = serde_json::to_string(&config).unwrap();
    let via_text: ResolvedConfig = serde_json::from_str(&text).unwrap();
    let via_value: ResolvedConfig =
        serde_json::from_value(serde_json::from_str::<serde_json::Value>(&text).unwrap()).unwrap();
    assert_eq!(via_text, config);
    assert_eq!(via_value, config);
}

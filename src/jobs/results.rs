//! An experiment's results, grouped by evaluation protocol. Each job's policy may be evaluated
//! many ways (the end of training, a deterministic check afterwards, 50 episodes in the user's
//! simulator through ONNX); per protocol a job's result is its newest succeeded evaluation under
//! it, and an arm's mean ± standard error is taken over the seeds with a result under one
//! protocol only. A stray evaluation of one seed adds a protocol beside the others and never
//! moves a mean.
//!
//! Which protocol a view shows: the one asked for, else the newest protocol every job with a
//! result has, else (no protocol is shared) the one most jobs have, said as such. The same rule
//! serves an experiment's grid and any set of jobs compared side by side.

use std::collections::{BTreeMap, BTreeSet};

use chrono::{DateTime, Utc};
use serde::Serialize;
use utoipa::ToSchema;

use crate::domain::experiment::{Arm, ExperimentRecord, Summary};
use crate::domain::{rfc3339, EvalProtocol, EvalRuntime, JobRecord, JobStatus, PolicyId};
use crate::store::{PageQuery, Store, StoreError};

/// Evaluations of one policy read to find its results (newest first); a policy evaluated more
/// often than this keeps the protocols of its newest ones.
const EVALUATIONS_READ: u32 = 1000;

/// One job of the grid and its metrics under the protocol shown.
#[derive(Clone, Debug, Serialize, ToSchema)]
pub struct JobResult {
    pub job_id: String,
    pub arm: String,
    pub seed: u64,
    pub status: JobStatus,
    pub policy_id: Option<String>,
    /// The key of the protocol `metrics` are under: the experiment's `protocol`, or absent when
    /// this job has no result under it.
    pub protocol: Option<String>,
    /// Every protocol this job has a result under (keys), newest first.
    pub protocols: Vec<String>,
    /// Where the metrics come from: `evaluation <id> (<source>, <env>)` or `in-training eval`;
    /// absent while there are none under the protocol shown.
    pub metrics_from: Option<String>,
    /// The paper's metrics (normalized_return, average_cost, cost_violation_ratio,
    /// cvar_cost_{50,20,10,5}, normalized_cost, …) under the protocol shown.
    pub metrics: BTreeMap<String, f64>,
}

/// An arm's results over its seeds, under one protocol.
#[derive(Clone, Debug, Serialize, ToSchema)]
pub struct ArmResult {
    pub label: String,
    pub algorithm: String,
    pub jobs: usize,
    pub succeeded: usize,
    /// Per metric: mean ± standard error over the seeds that have it under the protocol, and
    /// the values.
    pub metrics: BTreeMap<String, Summary>,
}

/// A protocol some of the experiment's jobs have results under.
#[derive(Clone, Debug, Serialize, ToSchema)]
pub struct ProtocolResult {
    pub protocol: EvalProtocol,
    /// Jobs with a result under it.
    pub jobs: usize,
    /// When its newest result was made.
    pub newest_at: String,
}

/// Why the view shows the protocol it shows.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, ToSchema)]
#[serde(rename_all = "snake_case")]
pub enum ProtocolChoice {
    /// Named by the request's `protocol`.
    Requested,
    /// The newest protocol every job with a result has.
    SharedByAll,
    /// No protocol is shared by every job with a result: the one most of them have (ties: the
    /// newest). The arms' means leave out the jobs without it.
    MostJobs,
}

/// A job's newest result under one protocol.
#[derive(Clone, Debug)]
struct Scored {
    protocol: EvalProtocol,
    at: DateTime<Utc>,
    from: String,
    metrics: BTreeMap<String, f64>,
}

/// A job and its results, newest protocol first.
#[derive(Clone, Debug)]
struct JobScores {
    job: JobResult,
    scored: Vec<Scored>,
}

/// Every job's results under every protocol (with the arms they are grouped in, for an
/// experiment).
#[derive(Clone, Debug)]
pub struct ExperimentScores {
    arms: Vec<Arm>,
    jobs: Vec<JobScores>,
}

/// What one view of the results shows.
#[derive(Clone, Debug)]
pub struct ResultsView {
    pub protocol: Option<EvalProtocol>,
    pub choice: Option<ProtocolChoice>,
    pub jobs: Vec<JobResult>,
    pub arms: Vec<ArmResult>,
}

/// Reads every job of the experiment and the results of its policy, in grid order (arm by arm,
/// each in the order of the experiment's seeds).
pub async fn scores(
    store: &Store,
    experiment: &ExperimentRecord,
) -> Result<ExperimentScores, StoreError> {
    let mut jobs = Vec::new();
    for job in store.experiment_jobs(&experiment.id).await? {
        jobs.push(job_scores(store, job).await?);
    }
    let spec = &experiment.spec;
    jobs.sort_by_key(|scores| {
        let arm = spec.arms.iter().position(|a| a.label() == scores.job.arm);
        (arm, spec.seeds.iter().position(|&s| s == scores.job.seed))
    });
    Ok(ExperimentScores { arms: spec.arms.clone(), jobs })
}

/// The results of the given jobs, in the order given (no arms: each job stands alone).
pub async fn scores_of_jobs(
    store: &Store,
    jobs: Vec<JobRecord>,
) -> Result<ExperimentScores, StoreError> {
    let mut scored = Vec::with_capacity(jobs.len());
    for job in jobs {
        scored.push(job_scores(store, job).await?);
    }
    Ok(ExperimentScores { arms: Vec::new(), jobs: scored })
}

async fn job_scores(store: &Store, job: JobRecord) -> Result<JobScores, StoreError> {
    let mut scored = match &job.policy_id {
        Some(policy) => evaluations(store, policy).await?,
        None => Vec::new(),
    };
    if scored.is_empty() {
        scored.extend(in_training(store, &job).await?);
    }
    let result = JobResult {
        job_id: job.id.to_string(),
        arm: job.experiment.map(|(_, arm)| arm).unwrap_or_default(),
        seed: job.config.seed(),
        status: job.status,
        policy_id: job.policy_id.map(|p| p.into_string()),
        protocols: scored.iter().map(|s| s.protocol.key.clone()).collect(),
        protocol: None,
        metrics_from: None,
        metrics: BTreeMap::new(),
    };
    Ok(JobScores { job: result, scored })
}

/// A policy's newest succeeded evaluation under each protocol, newest first.
async fn evaluations(store: &Store, policy: &PolicyId) -> Result<Vec<Scored>, StoreError> {
    let page = PageQuery { limit: EVALUATIONS_READ, offset: 0, after: None };
    let (evaluations, _) = store.list_evaluations(Some(policy), &page).await?;
    let mut seen = BTreeSet::new();
    Ok(evaluations
        .into_iter()
        .filter_map(|e| {
            let protocol = e.protocol();
            let report = e.report?;
            if !seen.insert(protocol.key.clone()) {
                return None;
            }
            let source = match e.training_step {
                Some(step) => format!("taken at training step {step}"),
                None => e.source.as_str().to_owned(),
            };
            Some(Scored {
                from: format!("evaluation {} ({source}, {})", e.id, report.env),
                metrics: named(report.metrics.named_values().to_vec()),
                at: e.created_at,
                protocol,
            })
        })
        .collect())
}

/// The job's last in-training `eval/*` values, if it evaluated itself: a job that never ended
/// with a policy (failed, cancelled) or one from before end-of-training evaluations were
/// stored. Under its `eval` block's protocol.
async fn in_training(store: &Store, job: &JobRecord) -> Result<Option<Scored>, StoreError> {
    let Some(eval) = &job.eval else { return Ok(None) };
    let last = store.last_metric_values(&job.id).await?;
    let metrics = named(last.iter().map(|(n, v)| (n.as_str(), *v)).collect());
    Ok((!metrics.is_empty()).then(|| Scored {
        protocol: EvalProtocol::new(&eval.spec(), EvalRuntime::Builtin),
        at: job.finished_at.unwrap_or(job.updated_at),
        from: "in-training eval".to_owned(),
        metrics,
    }))
}

/// `eval/<name>` values under their plain names.
fn named<S: AsRef<str>>(values: Vec<(S, f64)>) -> BTreeMap<String, f64> {
    values
        .into_iter()
        .filter_map(|(name, v)| Some((name.as_ref().strip_prefix("eval/")?.to_owned(), v)))
        .collect()
}

impl ExperimentScores {
    /// Every protocol with a result, most jobs first (ties: the newest first).
    pub fn protocols(&self) -> Vec<ProtocolResult> {
        let mut found: BTreeMap<&str, (EvalProtocol, usize, DateTime<Utc>)> = BTreeMap::new();
        for scored in self.jobs.iter().flat_map(|j| &j.scored) {
            let entry = found
                .entry(&scored.protocol.key)
                .or_insert_with(|| (scored.protocol.clone(), 0, scored.at));
            entry.1 += 1;
            entry.2 = entry.2.max(scored.at);
        }
        let mut protocols: Vec<_> = found.into_values().collect();
        protocols.sort_by(|a, b| b.1.cmp(&a.1).then(b.2.cmp(&a.2)));
        protocols
            .into_iter()
            .map(|(protocol, jobs, at)| ProtocolResult { protocol, jobs, newest_at: rfc3339(&at) })
            .collect()
    }

    /// The protocol a view shows when none is asked for (None while no job has a result).
    pub fn default_protocol(&self) -> Option<(EvalProtocol, ProtocolChoice)> {
        let with_results = self.jobs.iter().filter(|j| !j.scored.is_empty()).count();
        let protocols = self.protocols();
        let newest_shared = protocols
            .iter()
            .filter(|p| p.jobs == with_results)
            .max_by(|a, b| a.newest_at.cmp(&b.newest_at));
        match newest_shared {
            Some(shared) => Some((shared.protocol.clone(), ProtocolChoice::SharedByAll)),
            None => protocols.first().map(|p| (p.protocol.clone(), ProtocolChoice::MostJobs)),
        }
    }

    /// The protocol named by `key`, if any job has a result under it.
    pub fn protocol(&self, key: &str) -> Option<EvalProtocol> {
        let mut all = self.jobs.iter().flat_map(|j| &j.scored);
        all.find(|s| s.protocol.key == key).map(|s| s.protocol.clone())
    }

    /// The results under the protocol `key` names (see [`Self::protocol`]), else the default.
    pub fn view(&self, requested: Option<EvalProtocol>) -> ResultsView {
        let (protocol, choice) = match requested {
            Some(protocol) => (Some(protocol), Some(ProtocolChoice::Requested)),
            None => self.default_protocol().unzip(),
        };
        let key = protocol.as_ref().map(|p| p.key.as_str());
        let jobs = self.jobs_under(key);
        let arms = self.arms_of(&jobs);
        ResultsView { protocol, choice, jobs, arms }
    }

    /// Every job, with its metrics under `key` (none where it has no result under it).
    pub fn jobs_under(&self, key: Option<&str>) -> Vec<JobResult> {
        self.jobs
            .iter()
            .map(|scores| {
                let mut job = scores.job.clone();
                if let Some(hit) =
                    scores.scored.iter().find(|s| Some(s.protocol.key.as_str()) == key)
                {
                    job.protocol = Some(hit.protocol.key.clone());
                    job.metrics_from = Some(hit.from.clone());
                    job.metrics = hit.metrics.clone();
                }
                job
            })
            .collect()
    }

    /// Each arm's mean ± standard error over the given jobs' metrics.
    pub fn arms_of(&self, jobs: &[JobResult]) -> Vec<ArmResult> {
        self.arms
            .iter()
            .map(|arm| {
                let label = arm.label();
                let mine: Vec<&JobResult> = jobs.iter().filter(|j| j.arm == label).collect();
                let names: BTreeSet<&String> = mine.iter().flat_map(|j| j.metrics.keys()).collect();
                let metrics = names
                    .into_iter()
                    .filter_map(|name| {
                        let values =
                            mine.iter().filter_map(|j| j.metrics.get(name).copied()).collect();
                        Summary::of(values).map(|s| (name.clone(), s))
                    })
                    .collect();
                ArmResult {
                    algorithm: arm.algorithm.to_string(),
                    jobs: mine.len(),
                    succeeded: mine.iter().filter(|j| j.status == JobStatus::Succeeded).count(),
                    label,
                    metrics,
                }
            })
            .collect()
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::algo::Algorithm;
    use crate::domain::EvalSpec;

    fn protocol(episodes: usize, deterministic: bool) -> EvalProtocol {
        let spec = EvalSpec { env: "six-rooms".into(), episodes, seed: 0, deterministic };
        EvalProtocol::new(&spec, EvalRuntime::Builtin)
    }

    fn job(seed: u64, scored: Vec<(EvalProtocol, i64, f64)>) -> JobScores {
        let scored: Vec<Scored> = scored
            .into_iter()
            .map(|(protocol, at, cost)| Scored {
                protocol,
                at: DateTime::from_timestamp(at, 0).unwrap(),
                from: format!("evaluation at {at}"),
                metrics: BTreeMap::from([("average_cost".to_owned(), cost)]),
            })
            .collect();
        JobScores {
            job: JobResult {
                job_id: format!("job-{seed}"),
                arm: "bc".into(),
                seed,
                status: JobStatus::Succeeded,
                policy_id: None,
                protocol: None,
                protocols: scored.iter().map(|s| s.protocol.key.clone()).collect(),
                metrics_from: None,
                metrics: BTreeMap::new(),
            },
            scored,
        }
    }

    fn experiment(jobs: Vec<JobScores>) -> ExperimentScores {
        let arms = vec![Arm { label: None, algorithm: Algorithm::Bc, config: None }];
        ExperimentScores { arms, jobs }
    }

    /// Three seeds evaluated with sampled actions, then seed 0 once more deterministically: the
    /// mean stays the sampled one, and the deterministic protocol is listed beside it.
    #[test]
    fn a_stray_evaluation_of_one_seed_never_moves_the_mean() {
        let (sampled, deterministic) = (protocol(10, false), protocol(10, true));
        let scores = experiment(vec![
            job(0, vec![(deterministic.clone(), 9, 0.0), (sampled.clone(), 1, 3.0)]),
            job(1, vec![(sampled.clone(), 2, 6.0)]),
            job(2, vec![(sampled.clone(), 3, 9.0)]),
        ]);
        let view = scores.view(None);
        assert_eq!(view.protocol.as_ref(), Some(&sampled));
        assert_eq!(view.choice, Some(ProtocolChoice::SharedByAll));
        let cost = &view.arms[0].metrics["average_cost"];
        assert_eq!((cost.mean, cost.n, cost.values.clone()), (6.0, 3, vec![3.0, 6.0, 9.0]));
        let protocols = scores.protocols();
        assert_eq!(
            protocols.iter().map(|p| (p.protocol.key.clone(), p.jobs)).collect::<Vec<_>>(),
            [(sampled.key.clone(), 3), (deterministic.key.clone(), 1)]
        );
        assert_eq!(view.jobs[0].protocols, [deterministic.key.clone(), sampled.key.clone()]);

        // Asked for, the deterministic protocol averages only the seed that has it.
        let asked = scores.view(scores.protocol(&deterministic.key));
        assert_eq!(asked.choice, Some(ProtocolChoice::Requested));
        let cost = &asked.arms[0].metrics["average_cost"];
        assert_eq!((cost.mean, cost.n), (0.0, 1));
        assert_eq!(asked.jobs[1].metrics_from, None);
        assert!(asked.jobs[1].metrics.is_empty());
        assert_eq!(scores.protocol("runtime=act;nothing"), None);
    }

    /// Of two protocols every job has, the newer; where none is shared, the one most jobs have.
    #[test]
    fn the_default_is_the_newest_shared_protocol_else_the_most_common() {
        let (a, b, c) = (protocol(10, false), protocol(20, false), protocol(30, false));
        let shared = experiment(vec![
            job(0, vec![(b.clone(), 8, 1.0), (a.clone(), 1, 1.0)]),
            job(1, vec![(b.clone(), 7, 1.0), (a.clone(), 2, 1.0)]),
        ]);
        assert_eq!(shared.default_protocol(), Some((b.clone(), ProtocolChoice::SharedByAll)));
        let split = experiment(vec![
            job(0, vec![(a.clone(), 1, 1.0)]),
            job(1, vec![(a.clone(), 2, 1.0)]),
            job(2, vec![(c.clone(), 9, 1.0)]),
            job(3, vec![]),
        ]);
        assert_eq!(split.default_protocol(), Some((a, ProtocolChoice::MostJobs)));
        assert_eq!(experiment(vec![job(0, vec![])]).default_protocol(), None);
    }
}

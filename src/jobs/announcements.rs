//! What one process of a fleet tells the others, over PostgreSQL's NOTIFY: a job or an
//! evaluation was queued, a running job's cancel was requested, a job changed. Each only hastens
//! what polling does anyway (the only way on SQLite); [`super::fleet`] listens.

use crate::store::{Backend, Store};

/// The notification channel every process listens on (PostgreSQL).
pub(super) const CHANNEL: &str = "safedice";

/// What one process tells the others.
#[derive(Clone, Debug, PartialEq, Eq)]
pub enum Announcement {
    /// A job was queued: idle workers claim.
    JobQueued,
    /// An evaluation was queued.
    EvaluationQueued,
    /// A cancel was requested for this running job: its worker stops now.
    Cancel(String),
    /// This job changed (progress or status): API nodes update its event streams.
    Changed(String),
}

impl Announcement {
    fn payload(&self) -> String {
        match self {
            Announcement::JobQueued => "job".to_owned(),
            Announcement::EvaluationQueued => "evaluation".to_owned(),
            Announcement::Cancel(id) => format!("cancel:{id}"),
            Announcement::Changed(id) => format!("changed:{id}"),
        }
    }

    pub(super) fn parse(payload: &str) -> Option<Announcement> {
        match payload.split_once(':') {
            None if payload == "job" => Some(Announcement::JobQueued),
            None if payload == "evaluation" => Some(Announcement::EvaluationQueued),
            Some(("cancel", id)) => Some(Announcement::Cancel(id.to_owned())),
            Some(("changed", id)) => Some(Announcement::Changed(id.to_owned())),
            _ => None,
        }
    }
}

/// Tells the other processes (PostgreSQL NOTIFY; nothing on SQLite, where they poll). In the
/// background: an announcement only hastens what polling does anyway, so it never delays or
/// fails the caller.
pub fn announce(store: &Store, announcement: Announcement) {
    if store.backend() != Backend::Postgres {
        return;
    }
    let store = store.clone();
    tokio::spawn(async move {
        if let Err(e) = store.notify(CHANNEL, &announcement.payload()).await {
            tracing::debug!(error = %e, "cannot notify the other processes");
        }
    });
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn announcements_survive_their_payload() {
        for announcement in [
            Announcement::JobQueued,
            Announcement::EvaluationQueued,
            Announcement::Cancel("job-1".into()),
            Announcement::Changed("abc:def".into()),
        ] {
            assert_eq!(Announcement::parse(&announcement.payload()), Some(announcement));
        }
        assert_eq!(Announcement::parse("reboot"), None);
    }
}

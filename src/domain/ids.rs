//! Ids of the stored resources. Each kind has its own type, so a job id cannot be passed where a
//! dataset id is meant; new ids are minted here and nowhere else (random UUIDs, so ids from
//! different processes on one database never collide, and their first 8 characters, the short
//! form the dashboard shows and `?q=` finds, tell them apart).

use std::fmt;

macro_rules! id_type {
    ($(#[$doc:meta])* $name:ident) => {
        $(#[$doc])*
        #[derive(Clone, Debug, PartialEq, Eq, Hash, PartialOrd, Ord)]
        #[derive(serde::Serialize, serde::Deserialize)]
        #[serde(transparent)]
        pub struct $name(String);

        impl $name {
            /// A new random id.
            pub fn generate() -> Self {
                $name(uuid::Uuid::new_v4().to_string())
            }

            pub fn as_str(&self) -> &str {
                &self.0
            }

            pub fn into_string(self) -> String {
                self.0
            }

            /// The first 8 characters: the short form the dashboard shows and `?q=` finds.
            pub fn short(&self) -> &str {
                self.0.get(..8).unwrap_or(&self.0)
            }
        }

        /// An id as given by a client or read from the store (not checked: an unknown id is
        /// simply not found).
        impl From<String> for $name {
            fn from(id: String) -> Self {
                $name(id)
            }
        }

        impl AsRef<str> for $name {
            fn as_ref(&self) -> &str {
                &self.0
            }
        }

        impl fmt::Display for $name {
            fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
                f.write_str(&self.0)
            }
        }

        impl PartialEq<str> for $name {
            fn eq(&self, other: &str) -> bool {
                self.0 == other
            }
        }
    };
}

id_type!(
    /// An uploaded dataset.
    DatasetId
);
id_type!(
    /// A training job.
    JobId
);
id_type!(
    /// A trained policy (the artefact of a succeeded job).
    PolicyId
);
id_type!(
    /// A policy evaluation.
    EvaluationId
);
id_type!(
    /// An experiment (a grid of jobs over algorithms and seeds).
    ExperimentId
);

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn generated_ids_are_distinct_uuids_and_serialize_as_plain_strings() {
        let (a, b) = (JobId::generate(), JobId::generate());
        assert_ne!(a, b);
        assert!(uuid::Uuid::parse_str(a.as_str()).is_ok());
        assert_eq!(serde_json::to_value(&a).unwrap(), serde_json::Value::String(a.to_string()));
        let back: JobId = serde_json::from_value(serde_json::to_value(&a).unwrap()).unwrap();
        assert_eq!(back, a);
    }
}

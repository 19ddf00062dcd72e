//! Named models for deployment: a model has numbered versions, each pointing at a trained
//! policy, and aliases (`production`, `staging`, any name) pointing at a version, so a deployed
//! agent keeps one name for the life of a deployment while the policy behind it changes.
//!
//! How an agent names what answers it ([`ModelRef`]): `name` (the latest version), `name@alias`,
//! or `name` with a version number. The alias goes inside the one path segment of the model's
//! name (`/v1/models/pilot@production/act`, `/v2/models/pilot@production/infer`) rather than in
//! a path of its own, because Open Inference Protocol clients (tritonclient among them) take a
//! model's name as one string: the same `pilot@production` then works in every client.

use serde::{Deserialize, Serialize};
use utoipa::ToSchema;

use super::PolicyId;

/// Longest model or alias name.
pub const MAX_NAME_CHARS: usize = 64;
/// Longest description of a model or a version.
pub const MAX_DESCRIPTION_CHARS: usize = 10_000;
/// Longest `actor` or `reason` of an alias move.
pub const MAX_ACTOR_CHARS: usize = 200;
/// A canary's share of requests is kept in basis points: 10,000 is every request.
pub const BASIS_POINTS: u32 = 10_000;
/// The alias name that means "the latest version" and so cannot be set.
pub const LATEST: &str = "latest";

/// The rule every model and alias name follows, as error messages state it.
pub const NAME_RULE: &str = "1-64 characters from ASCII letters, digits and `- _ .`, starting \
     with a letter or a digit";

/// A model's name, checked ([`ModelName::parse`]): how the service carries one past the edge.
#[derive(Clone, Debug, PartialEq, Eq, Hash, PartialOrd, Ord, Serialize)]
#[serde(transparent)]
pub struct ModelName(String);

/// An alias's name, checked ([`AliasName::parse`]).
#[derive(Clone, Debug, PartialEq, Eq, Hash, PartialOrd, Ord, Serialize)]
#[serde(transparent)]
pub struct AliasName(String);

impl ModelName {
    /// `text` if it follows the rules of [`check_model_name`]; else what is wrong with it.
    pub fn parse(text: &str) -> Result<ModelName, String> {
        check_model_name(text).map(|()| ModelName(text.to_owned()))
    }

    pub fn as_str(&self) -> &str {
        &self.0
    }
}

impl AliasName {
    /// `text` if it follows the rules of [`check_alias_name`]; else what is wrong with it.
    pub fn parse(text: &str) -> Result<AliasName, String> {
        check_alias_name(text).map(|()| AliasName(text.to_owned()))
    }

    pub fn as_str(&self) -> &str {
        &self.0
    }
}

impl std::fmt::Display for ModelName {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(&self.0)
    }
}

impl std::fmt::Display for AliasName {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(&self.0)
    }
}

/// Checks a model's name: [`NAME_RULE`], and not of the form of a policy id (a UUID), so
/// `/v2/models/{name}` is never ambiguous between a model and a policy.
fn check_model_name(name: &str) -> Result<(), String> {
    check_name("model name", name)?;
    if uuid::Uuid::try_parse(name).is_ok() {
        return Err(format!(
            "model name {name:?} has the form of a policy id; policies are served under their \
             id already, so a model needs another name"
        ));
    }
    Ok(())
}

/// Checks an alias's name: [`NAME_RULE`], not all digits (that reads as a version number) and
/// not `latest` in any case (which always means the newest version: `LATEST` beside `latest`
/// would read as the same word and answer another version).
fn check_alias_name(alias: &str) -> Result<(), String> {
    check_name("alias", alias)?;
    if alias.chars().all(|c| c.is_ascii_digit()) {
        return Err(format!("alias {alias:?} is all digits, which reads as a version number"));
    }
    if alias.eq_ignore_ascii_case(LATEST) {
        return Err(format!("alias `{LATEST}` is reserved: it always means the newest version"));
    }
    Ok(())
}

/// Only ASCII: look-alike letters from other scripts and invisible or direction-changing
/// characters (U+202E) would make two different names read the same.
fn check_name(what: &str, name: &str) -> Result<(), String> {
    let allowed = |c: char| c.is_ascii_alphanumeric() || "-_.".contains(c);
    let starts_well = name.chars().next().is_some_and(|c| c.is_ascii_alphanumeric());
    let chars = name.chars().count();
    if chars == 0 || chars > MAX_NAME_CHARS || !starts_well || !name.chars().all(allowed) {
        return Err(format!("{what} {name:?} breaks the rule: {NAME_RULE}"));
    }
    Ok(())
}

/// Checks free text (a description, an actor, a reason): at most `max` characters, no control
/// characters but newlines and tabs.
pub fn check_text(field: &str, text: &str, max: usize) -> Result<(), String> {
    let chars = text.chars().count();
    if chars > max {
        return Err(format!("{field}: at most {max} characters, got {chars}"));
    }
    if text.chars().any(|c| c.is_control() && c != '\n' && c != '\t') {
        return Err(format!("{field}: control characters are not allowed"));
    }
    if let Some(c) = text.chars().find(|&c| super::labels::is_bidi_control(c)) {
        return Err(format!("{field}: U+{:04X} changes the direction text is shown in", c as u32));
    }
    Ok(())
}

/// Which version of a model answers.
#[derive(Clone, Debug, PartialEq, Eq)]
pub enum Selector {
    /// The highest-numbered version.
    Latest,
    /// The version an alias points at (or its canary's, for its share of requests).
    Alias(AliasName),
    /// A version by number.
    Version(u32),
}

/// A model as a deployed agent names it: `name`, `name@alias`, and a version by number from a
/// route's `/versions/{n}`.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct ModelRef {
    pub model: ModelName,
    pub selector: Selector,
}

impl ModelRef {
    /// `name` or `name@alias` (`name@latest`, in any case, is `name`).
    pub fn parse(text: &str) -> Result<ModelRef, String> {
        let (model, selector) = match text.split_once('@') {
            None => (text, Selector::Latest),
            Some((model, alias)) if alias.eq_ignore_ascii_case(LATEST) => (model, Selector::Latest),
            Some((model, alias)) => (model, Selector::Alias(AliasName::parse(alias)?)),
        };
        Ok(ModelRef { model: ModelName::parse(model)?, selector })
    }

    /// `name` with version `version` (from a route's `/versions/{n}`; `text` may not carry an
    /// alias then).
    pub fn with_version(text: &str, version: &str) -> Result<ModelRef, String> {
        let model = ModelName::parse(text)?;
        let number = version
            .parse::<u32>()
            .ok()
            .filter(|&n| n > 0)
            .ok_or_else(|| format!("version {version:?} is not a version number (1, 2, …)"))?;
        Ok(ModelRef { model, selector: Selector::Version(number) })
    }
}

impl std::fmt::Display for ModelRef {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match &self.selector {
            Selector::Latest => write!(f, "{}", self.model),
            Selector::Alias(alias) => write!(f, "{}@{alias}", self.model),
            Selector::Version(n) => write!(f, "{} version {n}", self.model),
        }
    }
}

/// A registered model.
#[derive(Clone, Debug, PartialEq)]
pub struct ModelRecord {
    pub name: String,
    pub description: String,
    pub tags: Vec<String>,
    /// The highest version number (None: no version yet).
    pub latest_version: Option<u32>,
    /// How many versions it has.
    pub version_count: u64,
    pub aliases: Vec<AliasRecord>,
    pub created_at: chrono::DateTime<chrono::Utc>,
    pub updated_at: chrono::DateTime<chrono::Utc>,
}

/// One version of a model: a policy, immutable once registered.
#[derive(Clone, Debug, PartialEq)]
pub struct ModelVersionRecord {
    pub model: String,
    pub version: u32,
    pub policy_id: PolicyId,
    /// The job that trained the policy, and its name.
    pub job_id: String,
    pub job_name: Option<String>,
    /// The algorithm that trained the policy.
    pub algorithm: String,
    pub description: String,
    /// Who registered it: `api`, or `job <id>` for a job's `register`.
    pub source: String,
    pub created_at: chrono::DateTime<chrono::Utc>,
}

/// A share of an alias's requests answered by another version.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize, ToSchema)]
pub struct Canary {
    pub version: u32,
    /// The share, in basis points (1-9,999 of every 10,000 requests).
    pub basis_points: u32,
}

/// A version run beside an alias's answer on a share of its requests and compared with it,
/// never returned (docs/shadow.md).
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize, ToSchema)]
pub struct Shadow {
    pub version: u32,
    /// The share of requests shadowed, in basis points (1-10,000 of every 10,000 requests).
    pub basis_points: u32,
}

/// Where an alias points.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct AliasTarget {
    pub version: u32,
    pub canary: Option<Canary>,
    pub shadow: Option<Shadow>,
}

impl AliasTarget {
    /// Every version the alias needs: its own, its canary's and its shadow's.
    pub fn versions(&self) -> impl Iterator<Item = u32> {
        let others = [self.canary.map(|c| c.version), self.shadow.map(|s| s.version)];
        std::iter::once(self.version).chain(others.into_iter().flatten())
    }
}

/// An alias of a model.
#[derive(Clone, Debug, PartialEq)]
pub struct AliasRecord {
    pub alias: String,
    pub target: AliasTarget,
    pub updated_at: chrono::DateTime<chrono::Utc>,
}

/// One move of an alias: who moved it when, from where to where (`to` None: deleted).
#[derive(Clone, Debug, PartialEq)]
pub struct AliasMove {
    /// Increases with every change of the model.
    pub seq: u64,
    pub alias: String,
    /// Where it pointed before (None: it was created).
    pub from: Option<AliasTarget>,
    pub to: Option<AliasTarget>,
    pub actor: String,
    pub reason: Option<String>,
    pub moved_at: chrono::DateTime<chrono::Utc>,
}

/// Who moves an alias and why, as the history keeps it; and the version the mover saw it at.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct MoveNote {
    pub actor: String,
    pub reason: Option<String>,
    /// The move only happens if the alias points at this version now (a page or script that
    /// read the alias, then moves it, does not undo a move someone made in between).
    pub expected_version: Option<u32>,
}

/// A job's `register`: its policy becomes the next version of `model` when it succeeds, and
/// `alias` (if given) moves to that version.
#[derive(Clone, Debug, PartialEq, Eq, Serialize, Deserialize, ToSchema)]
#[serde(deny_unknown_fields)]
pub struct Registration {
    /// An existing model's name.
    #[schema(pattern = "^[A-Za-z0-9][A-Za-z0-9._-]*$", min_length = 1, max_length = 64)]
    pub model: String,
    /// An alias to point at the new version (created if the model has none of that name).
    #[schema(
        pattern = r"^(?:[A-Za-z][A-Za-z0-9._-]*|[0-9]+[A-Za-z._-][A-Za-z0-9._-]*)$",
        max_length = 64
    )]
    pub alias: Option<String>,
}

impl Registration {
    /// The model's name, once the model's and the alias's names are checked.
    pub fn validated(&self) -> Result<ModelName, String> {
        let model = ModelName::parse(&self.model).map_err(|e| format!("register.model: {e}"))?;
        if let Some(alias) = &self.alias {
            AliasName::parse(alias).map_err(|e| format!("register.alias: {e}"))?;
        }
        Ok(model)
    }
}

/// What serving needs of a model: the policy behind each version, its latest version and its
/// aliases, as of `revision`.
#[derive(Clone, Debug, PartialEq)]
pub struct ModelRoutes {
    pub name: String,
    /// The model row's creation stamp as stored (tells a re-created model from the deleted one).
    pub created_at: String,
    pub revision: u64,
    pub versions: Vec<(u32, PolicyId)>,
    pub aliases: Vec<(String, AliasTarget)>,
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn references_name_a_model_and_its_alias_or_the_latest_version() {
        let parsed = ModelRef::parse("pilot@production").unwrap();
        assert_eq!(parsed.selector, Selector::Alias(AliasName::parse("production").unwrap()));
        assert_eq!(parsed.to_string(), "pilot@production");
        assert_eq!(ModelRef::parse("pilot").unwrap().selector, Selector::Latest);
        assert_eq!(ModelRef::parse("pilot@latest").unwrap().selector, Selector::Latest);
        assert_eq!(ModelRef::with_version("pilot", "3").unwrap().selector, Selector::Version(3));
        assert!(ModelRef::with_version("pilot", "0").is_err());
        assert!(ModelRef::with_version("pilot@x", "1").is_err());
    }

    #[test]
    fn names_that_could_read_as_another_are_refused_with_the_rule() {
        for bad in ["", "-lead", "a/b", "a b", "a@b", "x\u{202e}y", "pіlot", &"a".repeat(65)] {
            let message = check_model_name(bad).unwrap_err();
            assert!(message.contains(NAME_RULE), "{bad:?}: {message}");
        }
        assert!(check_model_name("6f1c0d2e-0000-4000-8000-000000000000")
            .unwrap_err()
            .contains("policy id"));
        assert!(check_alias_name("42").unwrap_err().contains("version number"));
        assert!(check_alias_name("latest").unwrap_err().contains("reserved"));
        for other_case in ["LATEST", "Latest", "laTest"] {
            assert!(check_alias_name(other_case).unwrap_err().contains("reserved"));
            assert_eq!(
                ModelRef::parse(&format!("pilot@{other_case}")).unwrap().selector,
                Selector::Latest
            );
        }
        for good in ["pilot", "Pilot_2.v1", "9lives", &"a".repeat(64)] {
            check_model_name(good).unwrap();
        }
    }
}

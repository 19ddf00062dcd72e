//! What people call a job: a name, tags and notes. They never change what the job computes, so
//! they can be edited at any time, also while it runs.

use serde::{Deserialize, Serialize};
use utoipa::ToSchema;

pub const MAX_NAME_CHARS: usize = 200;
pub const MAX_TAGS: usize = 32;
pub const MAX_TAG_CHARS: usize = 64;
pub const MAX_NOTES_CHARS: usize = 10_000;

/// A tag as the API describes it (request bodies declare their tags as a list of these), so
/// clients and schema-driven testers know the rule [`check_tag`] enforces.
pub struct TagSchema;

impl utoipa::PartialSchema for TagSchema {
    fn schema() -> utoipa::openapi::RefOr<utoipa::openapi::schema::Schema> {
        use utoipa::openapi::schema::{ObjectBuilder, Type};
        ObjectBuilder::new()
            .schema_type(Type::String)
            .pattern(Some(TAG_PATTERN))
            .min_length(Some(1))
            .max_length(Some(MAX_TAG_CHARS))
            .description(Some("1-64 characters from letters, digits and `- _ . : / =`"))
            .into()
    }
}

impl ToSchema for TagSchema {
    fn name() -> std::borrow::Cow<'static, str> {
        "Tag".into()
    }
}

/// [`check_tag`]'s rule as a regular expression.
pub const TAG_PATTERN: &str = "^[A-Za-z0-9._:/=-]{1,64}$";

/// [`check_text`]'s rule for one line (a name) as a regular expression: no control characters,
/// nor the invisible characters that change the direction text is shown in.
pub const LINE_PATTERN: &str =
    r"^[^\x00-\x1f\x7f-\x9f\u061c\u200e\u200f\u202a-\u202e\u2066-\u2069]*$";
/// The same for prose (notes), where tabs and newlines are allowed.
pub const PROSE_PATTERN: &str =
    r"^[^\x00-\x08\x0b-\x1f\x7f-\x9f\u061c\u200e\u200f\u202a-\u202e\u2066-\u2069]*$";

/// A job's name as the API describes it, in every body that sets one.
pub struct JobNameSchema;

impl utoipa::PartialSchema for JobNameSchema {
    fn schema() -> utoipa::openapi::RefOr<utoipa::openapi::schema::Schema> {
        text_schema(LINE_PATTERN, MAX_NAME_CHARS, "Free text, at most 200 characters, no control characters (nor the invisible characters that change the direction text is shown in)")
    }
}

impl ToSchema for JobNameSchema {
    fn name() -> std::borrow::Cow<'static, str> {
        "JobName".into()
    }
}

/// A job's notes as the API describes them, in every body that sets them.
pub struct JobNotesSchema;

impl utoipa::PartialSchema for JobNotesSchema {
    fn schema() -> utoipa::openapi::RefOr<utoipa::openapi::schema::Schema> {
        text_schema(
            PROSE_PATTERN,
            MAX_NOTES_CHARS,
            "Free text, at most 10,000 characters; no control characters but tabs and newlines",
        )
    }
}

impl ToSchema for JobNotesSchema {
    fn name() -> std::borrow::Cow<'static, str> {
        "JobNotes".into()
    }
}

fn text_schema(
    pattern: &str,
    max: usize,
    description: &str,
) -> utoipa::openapi::RefOr<utoipa::openapi::schema::Schema> {
    use utoipa::openapi::schema::{ObjectBuilder, Type};
    ObjectBuilder::new()
        .schema_type(Type::String)
        .pattern(Some(pattern))
        .max_length(Some(max))
        .description(Some(description))
        .into()
}

/// A job's name, tags and notes.
#[derive(Clone, Debug, Default, PartialEq, Eq, Serialize, Deserialize, ToSchema)]
pub struct JobLabels {
    /// Free text, at most 200 characters, no control characters (nor the invisible characters
    /// that change the direction text is shown in).
    #[schema(value_type = Option<JobNameSchema>)]
    pub name: Option<String>,
    /// Up to 32 tags of 1-64 characters from letters, digits and `- _ . : / =`
    /// (e.g. `env=point-goal`), kept in the order given, duplicates dropped.
    pub tags: Vec<String>,
    /// Free text, at most 10,000 characters.
    #[schema(value_type = Option<JobNotesSchema>)]
    pub notes: Option<String>,
}

impl JobLabels {
    /// Checks every field, trimming the name and dropping repeated tags; the error names the
    /// field and the rule.
    pub fn validated(self) -> Result<JobLabels, String> {
        let name = match self.name.map(|n| n.trim().to_owned()) {
            Some(n) if n.is_empty() => None,
            Some(n) => Some(check_text("name", n, MAX_NAME_CHARS, false)?),
            None => None,
        };
        let notes = match self.notes {
            Some(n) if n.trim().is_empty() => None,
            Some(n) => Some(check_text("notes", n, MAX_NOTES_CHARS, true)?),
            None => None,
        };
        if self.tags.len() > MAX_TAGS {
            return Err(format!("tags: at most {MAX_TAGS} tags, got {}", self.tags.len()));
        }
        let mut tags: Vec<String> = Vec::with_capacity(self.tags.len());
        for tag in self.tags {
            check_tag(&tag)?;
            if !tags.contains(&tag) {
                tags.push(tag);
            }
        }
        Ok(JobLabels { name, tags, notes })
    }
}

/// A tag: 1-64 characters from letters, digits and `- _ . : / =`.
pub fn check_tag(tag: &str) -> Result<(), String> {
    let allowed = |c: char| c.is_ascii_alphanumeric() || "-_.:/=".contains(c);
    let chars = tag.chars().count();
    if chars == 0 || chars > MAX_TAG_CHARS || !tag.chars().all(allowed) {
        return Err(format!(
            "tags: {tag:?} is not a tag (1-{MAX_TAG_CHARS} characters from letters, digits and \
             `- _ . : / =`)"
        ));
    }
    Ok(())
}

fn check_text(field: &str, text: String, max: usize, newlines: bool) -> Result<String, String> {
    let chars = text.chars().count();
    if chars > max {
        return Err(format!("{field}: at most {max} characters, got {chars}"));
    }
    let control = |c: char| c.is_control() && !(newlines && (c == '\n' || c == '\t'));
    if text.chars().any(control) {
        return Err(format!("{field}: control characters are not allowed"));
    }
    if let Some(c) = text.chars().find(|&c| is_bidi_control(c)) {
        return Err(format!(
            "{field}: U+{:04X} changes the direction text is shown in (a name could then read \
             as another); write the text without it",
            c as u32
        ));
    }
    Ok(text)
}

/// The Unicode bidirectional formatting characters (embeddings, overrides, isolates, marks):
/// invisible, and they reorder what follows them on screen.
pub fn is_bidi_control(c: char) -> bool {
    matches!(c, '\u{061C}' | '\u{200E}' | '\u{200F}' | '\u{202A}'..='\u{202E}' | '\u{2066}'..='\u{2069}')
}

#[cfg(test)]
mod tests {
    use super::*;

    fn labels(name: Option<&str>, tags: &[&str], notes: Option<&str>) -> JobLabels {
        JobLabels {
            name: name.map(str::to_owned),
            tags: tags.iter().map(|t| t.to_string()).collect(),
            notes: notes.map(str::to_owned),
        }
    }

    #[test]
    fn valid_labels_are_trimmed_and_deduplicated() {
        let got = labels(Some("  baseline run "), &["env=point-goal", "a", "env=point-goal"], None)
            .validated()
            .unwrap();
        assert_eq!(got, labels(Some("baseline run"), &["env=point-goal", "a"], None));
        assert_eq!(labels(Some("  "), &[], Some(" ")).validated().unwrap(), JobLabels::default());
        assert!(labels(None, &[], Some("line one\nline two")).validated().is_ok());
    }

    #[test]
    fn bad_labels_are_refused_with_the_field_named() {
        let long = "x".repeat(MAX_NAME_CHARS + 1);
        let cases = [
            (labels(Some(&long), &[], None), "name: at most 200"),
            (labels(Some("a\u{7}b"), &[], None), "name: control"),
            (labels(Some("invoice\u{202e}fdp.exe"), &[], None), "name: U+202E"),
            (labels(None, &[], Some("note \u{2066}x")), "notes: U+2066"),
            (labels(None, &["has space"], None), "tags: \"has space\""),
            (labels(None, &[""], None), "tags: \"\""),
            (labels(None, &["%"], None), "tags: \"%\""),
        ];
        for (input, want) in cases {
            let err = input.validated().unwrap_err();
            assert!(err.starts_with(want), "{err}");
        }
        let many: Vec<String> = (0..=MAX_TAGS).map(|i| format!("t{i}")).collect();
        let err = JobLabels { tags: many, ..Default::default() }.validated().unwrap_err();
        assert!(err.starts_with("tags: at most 32"), "{err}");
    }
}

//! Bounded text: messages that may quote what a client sent (a JSONL line, an `.npy` header, a
//! CSV cell) are cut to a few hundred bytes so that an error answer stays small whatever the
//! input holds.

/// The longest message an error carries, in bytes (after [`bounded`]).
pub const MAX_MESSAGE_BYTES: usize = 1024;

/// `text` unchanged when it fits in `max` bytes; otherwise its head and tail with ` … ` (and
/// the number of bytes left out) between them, cut on character boundaries, at most `max` bytes.
/// The head says where the problem is and the tail usually says how to fix it, so both stay.
pub fn bounded(text: String, max: usize) -> String {
    if text.len() <= max {
        return text;
    }
    // " … [N bytes omitted] … " with N of up to 20 digits.
    let marker_room = 48;
    let keep = max.saturating_sub(marker_room);
    let head_end = floor_char_boundary(&text, keep * 2 / 3);
    let tail_start = ceil_char_boundary(&text, text.len() - (keep - head_end));
    let omitted = tail_start - head_end;
    format!("{} … [{omitted} bytes omitted] … {}", &text[..head_end], &text[tail_start..])
}

/// [`bounded`] with [`MAX_MESSAGE_BYTES`].
pub fn bounded_message(text: String) -> String {
    bounded(text, MAX_MESSAGE_BYTES)
}

fn floor_char_boundary(text: &str, mut index: usize) -> usize {
    index = index.min(text.len());
    while !text.is_char_boundary(index) {
        index -= 1;
    }
    index
}

fn ceil_char_boundary(text: &str, mut index: usize) -> usize {
    index = index.min(text.len());
    while !text.is_char_boundary(index) {
        index += 1;
    }
    index
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn short_text_is_unchanged() {
        assert_eq!(bounded("line 3: `obs` is empty".into(), 100), "line 3: `obs` is empty");
    }

    #[test]
    fn long_text_keeps_head_and_tail_within_the_limit() {
        let text = format!("line 1: {} is not a number; fix it", "9".repeat(50_000_000 / 1000));
        let cut = bounded(text.clone(), 200);
        assert!(cut.len() <= 200, "{} bytes", cut.len());
        assert!(cut.starts_with("line 1: 999"), "{cut}");
        assert!(cut.ends_with("; fix it"), "{cut}");
        assert!(cut.contains("bytes omitted"), "{cut}");
    }

    #[test]
    fn multibyte_characters_are_never_split() {
        for len in 0..40 {
            let text = "é€😀".repeat(100 + len);
            let cut = bounded(text, 120 + len);
            assert!(cut.len() <= 120 + len);
            assert!(cut.contains(" … ["));
        }
    }
}

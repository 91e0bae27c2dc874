//! User values quoted in messages, bounded: an error about a 10 MB line or a number written as
//! `1e300` must stay one readable line, not the whole value (301 digits for `1e300` in Rust's
//! plain `{}`). Every error path that repeats what the user wrote goes through [`quote`] (text)
//! or [`num`] (numbers).

/// The most characters of a user's value repeated in a message: enough to recognise a key, a
/// path or a number; the rest is counted, not shown.
pub const MAX_QUOTED_CHARS: usize = 60;

/// `text` in double quotes, at most [`MAX_QUOTED_CHARS`] characters of it (then `...` and its
/// length in bytes), control characters written as escapes so that a message stays one line.
pub fn quote(text: &str) -> String {
    let (shown, cut) = bounded(text);
    match cut {
        false => format!("\"{shown}\""),
        true => format!("\"{shown}...\" ({} bytes)", text.len()),
    }
}

/// [`quote`] without the quotes, for messages that show a value bare (`--camera SPEC: ...`).
pub fn excerpt(text: &str) -> String {
    let (shown, cut) = bounded(text);
    match cut {
        false => shown,
        true => format!("{shown}... ({} bytes)", text.len()),
    }
}

/// At most [`MAX_QUOTED_CHARS`] characters of `text`, control characters escaped, and whether
/// it was cut.
fn bounded(text: &str) -> (String, bool) {
    let mut out = String::new();
    for (n, c) in text.chars().enumerate() {
        if n == MAX_QUOTED_CHARS {
            return (out, true);
        }
        if c.is_control() {
            out.extend(c.escape_default());
        } else {
            out.push(c);
        }
    }
    (out, false)
}

/// A number for a message, at most about 25 characters: plain (`0.5`, `1280`) between 1e-4 and
/// 1e15 in magnitude, else in exponent form (`1e300`, `2.5e-7`); `NaN`, `inf` and `-inf` as such.
pub fn num(v: f64) -> String {
    let a = v.abs();
    if !v.is_finite() || a == 0.0 || (1e-4..1e15).contains(&a) {
        format!("{v}")
    } else {
        format!("{v:e}")
    }
}

/// Numbers as a user reads them: `(a, b, c)`, each by [`num`] (never Rust's `[a, b, c]` debug
/// form).
pub fn numbers(values: &[f64]) -> String {
    let parts: Vec<String> = values.iter().map(|&v| num(v)).collect();
    format!("({})", parts.join(", "))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn numbers_are_listed_in_parentheses() {
        assert_eq!(numbers(&[1.0, -2.5, 1e300]), "(1, -2.5, 1e300)");
        assert_eq!(numbers(&[]), "()");
    }

    #[test]
    fn long_values_are_cut_and_counted() {
        assert_eq!(quote("abc"), "\"abc\"");
        let long = "x".repeat(10_000_000);
        let q = quote(&long);
        assert!(q.len() < 100, "{}", q.len());
        assert!(q.ends_with("...\" (10000000 bytes)"), "{q}");
        assert_eq!(quote("a\nb\u{1b}"), "\"a\\nb\\u{1b}\"");
        assert_eq!(excerpt("v4l2:/dev/video0"), "v4l2:/dev/video0");
        assert!(excerpt(&long).ends_with("x... (10000000 bytes)"));
        // Cut on characters, never inside one.
        let wide = "\u{00e9}".repeat(100);
        assert!(quote(&wide).starts_with(&format!("\"{}...", "\u{00e9}".repeat(60))));
    }

    #[test]
    fn numbers_stay_short() {
        assert_eq!(num(1e300), "1e300");
        assert_eq!(num(-2.5e-7), "-2.5e-7");
        assert_eq!(num(640.0), "640");
        assert_eq!(num(0.25), "0.25");
        assert_eq!(num(0.0), "0");
        assert_eq!(num(f64::NAN), "NaN");
        assert_eq!(num(f64::NEG_INFINITY), "-inf");
        assert!(num(f64::MAX).len() < 30);
        assert!(num(f64::MIN_POSITIVE).len() < 30);
    }
}

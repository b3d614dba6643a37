//! Numbers for people: a few significant digits, thousands separators, units, a dash for
//! "no value" — never `Some(…)` and never sixteen digits.

/// The text shown where a value is missing (no fit, no frame, nothing to measure).
pub const MISSING: &str = "–";

/// `x` with `digits` significant digits (at least 1), in plain notation between 1e-4 and 1e6 and
/// in scientific notation (`1.2e-7`) outside; trailing zeros are kept, so a column reads evenly.
/// Non-finite values are written as `inf`, `-inf`, `NaN`.
pub fn sig(x: f64, digits: usize) -> String {
    let digits = digits.max(1);
    if !x.is_finite() {
        return format!("{x}");
    }
    if x == 0.0 {
        return if digits > 1 {
            format!("{:.*}", digits - 1, 0.0)
        } else {
            "0".into()
        };
    }
    let a = x.abs();
    if !(1e-4..1e6).contains(&a) {
        return format!("{:.*e}", digits - 1, x);
    }
    // Digits after the point so that `digits` significant ones show; rounding may carry into a
    // new leading digit (9.996 → 10.0), so the magnitude is taken after rounding.
    let mag = a.log10().floor() as i32;
    let decimals = (digits as i32 - 1 - mag).max(0) as usize;
    let s = format!("{:.*}", decimals, x);
    let rounded: f64 = s.parse().unwrap_or(x);
    let mag2 = rounded.abs().log10().floor() as i32;
    if mag2 > mag && decimals > 0 {
        format!("{:.*}", decimals - 1, x)
    } else {
        s
    }
}

/// `x` with `decimals` digits after the point.
pub fn fixed(x: f64, decimals: usize) -> String {
    if x.is_finite() {
        format!("{x:.decimals$}")
    } else {
        format!("{x}")
    }
}

/// A log E value (Eq. 8): three significant digits.
pub fn log_e(x: f64) -> String {
    sig(x, 3)
}

/// `f(x)` or [`MISSING`].
pub fn opt(x: Option<f64>, f: impl Fn(f64) -> String) -> String {
    x.map_or_else(|| MISSING.to_string(), f)
}

/// Per-channel values `r / g / b` with `f`, [`MISSING`] for a channel without one.
pub fn rgb(v: [Option<f64>; 3], f: impl Fn(f64) -> String) -> String {
    v.map(|x| opt(x, &f)).join(" / ")
}

/// The mean of the channels that have a value.
pub fn channel_mean(v: [Option<f64>; 3]) -> Option<f64> {
    let x: Vec<f64> = v.iter().flatten().copied().collect();
    (!x.is_empty()).then(|| x.iter().sum::<f64>() / x.len() as f64)
}

/// A count with thousands separators: `12,345`.
pub fn count(n: usize) -> String {
    let s = n.to_string();
    let mut out = String::with_capacity(s.len() + s.len() / 3);
    for (k, ch) in s.chars().enumerate() {
        if k > 0 && (s.len() - k).is_multiple_of(3) {
            out.push(',');
        }
        out.push(ch);
    }
    out
}

/// A duration: `0.42 s`, `12.3 s`, `2 min 05 s`.
pub fn seconds(s: f64) -> String {
    if !s.is_finite() {
        return MISSING.into();
    }
    if s < 60.0 {
        format!("{} s", sig(s, if s < 1.0 { 2 } else { 3 }))
    } else {
        let whole = s.round() as u64;
        format!("{} min {:02} s", whole / 60, whole % 60)
    }
}

/// A fraction as a percentage with `decimals` digits: `0.0123` → `1.23 %`.
pub fn percent(fraction: f64, decimals: usize) -> String {
    format!("{} %", fixed(100.0 * fraction, decimals))
}

/// A size in bytes: `812 B`, `45.3 kB`, `1.20 MB`.
pub fn bytes(n: u64) -> String {
    let x = n as f64;
    if x < 1e3 {
        format!("{n} B")
    } else if x < 1e6 {
        format!("{} kB", sig(x / 1e3, 3))
    } else if x < 1e9 {
        format!("{} MB", sig(x / 1e6, 3))
    } else {
        format!("{} GB", sig(x / 1e9, 3))
    }
}

/// A snake_case or CamelCase identifier as words: `NoData` → `no data`, `too_few` → `too few`.
pub fn words(id: &str) -> String {
    let mut out = String::new();
    for (k, ch) in id.chars().enumerate() {
        if ch == '_' {
            out.push(' ');
        } else if ch.is_uppercase() {
            if k > 0 && !out.ends_with(' ') {
                out.push(' ');
            }
            out.extend(ch.to_lowercase());
        } else {
            out.push(ch);
        }
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn significant_digits_read_like_a_person_wrote_them() {
        assert_eq!(sig(0.009_123_456_789, 3), "0.00912");
        assert_eq!(sig(0.046_712_345_678_901_23, 3), "0.0467");
        assert_eq!(sig(12.345, 3), "12.3");
        assert_eq!(sig(9.996, 3), "10.0");
        assert_eq!(sig(0.099_96, 2), "0.10");
        assert_eq!(sig(123_456.0, 3), "123456");
        assert_eq!(sig(1.234e-7, 2), "1.2e-7");
        assert_eq!(sig(3.2e9, 2), "3.2e9");
        assert_eq!(sig(-0.5, 2), "-0.50");
        assert_eq!(sig(0.0, 3), "0.00");
        assert_eq!(sig(f64::NAN, 3), "NaN");
        assert_eq!(log_e(0.014_999_999_999), "0.0150");
    }

    #[test]
    fn counts_durations_percentages_and_missing_values() {
        assert_eq!(count(0), "0");
        assert_eq!(count(999), "999");
        assert_eq!(count(1000), "1,000");
        assert_eq!(count(1_234_567), "1,234,567");
        assert_eq!(seconds(0.4237), "0.42 s");
        assert_eq!(seconds(12.34), "12.3 s");
        assert_eq!(seconds(125.4), "2 min 05 s");
        assert_eq!(percent(0.012_345, 2), "1.23 %");
        assert_eq!(bytes(812), "812 B");
        assert_eq!(bytes(1_203_000), "1.20 MB");
        assert_eq!(
            rgb([Some(0.046_71), None, Some(0.01)], log_e),
            "0.0467 / – / 0.0100"
        );
        assert_eq!(channel_mean([Some(1.0), None, Some(3.0)]), Some(2.0));
        assert_eq!(channel_mean([None; 3]), None);
        assert_eq!(words("NoData"), "no data");
        assert_eq!(words("too_few_samples"), "too few samples");
    }
}

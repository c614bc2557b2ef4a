//! Lists of episode seeds as operators write them: `0..1000`, `5..=9`, `7`,
//! or a comma-separated mix.

use std::str::FromStr;

/// An ordered list of episode seeds.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct Seeds(pub Vec<u64>);

/// A seed list that does not parse.
#[derive(Debug, thiserror::Error, PartialEq, Eq)]
#[error("invalid seed list `{text}`: {reason} (write e.g. `0..1000`, `5..=9` or `1,2,3`)")]
pub struct SeedsError {
    text: String,
    reason: String,
}

/// Most seeds one list may hold.
const MAX_SEEDS: u64 = 10_000_000;

impl FromStr for Seeds {
    type Err = SeedsError;

    fn from_str(text: &str) -> Result<Self, Self::Err> {
        let error = |reason: String| SeedsError {
            text: text.to_string(),
            reason,
        };
        let number = |s: &str| {
            s.trim()
                .parse::<u64>()
                .map_err(|e| error(format!("`{}`: {e}", s.trim())))
        };
        let mut seeds = Vec::new();
        for part in text.split(',') {
            let (lo, hi) = if let Some((a, b)) = part.split_once("..=") {
                (
                    number(a)?,
                    number(b)?
                        .checked_add(1)
                        .ok_or_else(|| error("range end overflows".into()))?,
                )
            } else if let Some((a, b)) = part.split_once("..") {
                (number(a)?, number(b)?)
            } else {
                let n = number(part)?;
                (n, n + 1)
            };
            if lo >= hi {
                return Err(error(format!("range `{}` is empty", part.trim())));
            }
            if (seeds.len() as u64).saturating_add(hi - lo) > MAX_SEEDS {
                return Err(error(format!("more than {MAX_SEEDS} seeds")));
            }
            seeds.extend(lo..hi);
        }
        Ok(Self(seeds))
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn parses_ranges_and_lists() {
        assert_eq!("0..3".parse::<Seeds>().unwrap().0, vec![0, 1, 2]);
        assert_eq!("5..=6, 9".parse::<Seeds>().unwrap().0, vec![5, 6, 9]);
        assert_eq!("0..1000".parse::<Seeds>().unwrap().0.len(), 1000);
    }

    #[test]
    fn malformed_seed_lists_are_refused() {
        for bad in ["", "a..b", "3..3", "9..2", "1,,2", "0..99999999999"] {
            let err = bad.parse::<Seeds>().unwrap_err();
            assert!(err.to_string().contains("invalid seed list"), "{err}");
        }
    }
}

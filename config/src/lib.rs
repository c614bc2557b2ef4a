//! Configuration files: reading a TOML file into a typed configuration,
//! the error every process reports a bad file with, naming the file or
//! the dotted path of the field that is wrong (`env.time_limit`), and
//! editing a file in place for the commands that write settings.

use serde::de::DeserializeOwned;
use std::path::Path;

/// A configuration value that is out of range, named by its TOML path.
#[derive(Debug, thiserror::Error, PartialEq)]
pub enum ConfigError {
    /// A field holds a value it must not.
    #[error("invalid config field `{field}`: {reason}")]
    Invalid {
        /// Dotted path of the field, as written in TOML.
        field: String,
        /// What is wrong with it.
        reason: String,
    },
    /// The TOML text does not parse or names unknown fields.
    #[error("invalid config: {0}")]
    Parse(String),
    /// The file cannot be read.
    #[error("cannot read config file {path}: {reason}")]
    Read {
        /// The file.
        path: String,
        /// The operating system's reason.
        reason: String,
    },
    /// The file cannot be written.
    #[error("cannot write config file {path}: {reason}")]
    Write {
        /// The file.
        path: String,
        /// The operating system's reason.
        reason: String,
    },
}

impl ConfigError {
    /// Field `field` (its dotted TOML path) holds a value it must not.
    pub fn invalid(field: &str, reason: impl Into<String>) -> Self {
        Self::Invalid {
            field: field.to_string(),
            reason: reason.into(),
        }
    }

    /// The same error for a configuration nested under `table` in a larger
    /// file: field `time_limit` becomes `env.time_limit`.
    pub fn in_table(self, table: &str) -> Self {
        match self {
            Self::Invalid { field, reason } => Self::Invalid {
                field: format!("{table}.{field}"),
                reason,
            },
            other => other,
        }
    }
}

/// Checks that `value`, the field `field`, is finite and within
/// `[lo, hi]`.
pub fn in_range(field: &str, value: f64, lo: f64, hi: f64) -> Result<(), ConfigError> {
    if value.is_finite() && (lo..=hi).contains(&value) {
        Ok(())
    } else {
        Err(ConfigError::invalid(
            field,
            format!("{value} must lie in [{lo}, {hi}]"),
        ))
    }
}

/// Reads and parses a TOML file into any configuration type; errors name
/// the file. Validation is the caller's.
pub fn read_toml<T: DeserializeOwned>(path: &Path) -> Result<T, ConfigError> {
    let text = std::fs::read_to_string(path).map_err(|e| ConfigError::Read {
        path: path.display().to_string(),
        reason: e.to_string(),
    })?;
    toml::from_str(&text).map_err(|e| ConfigError::Parse(format!("{}: {e}", path.display())))
}

/// Edits the TOML file at `path` (created when missing) with `edit`,
/// keeping every other setting and comment, and writes it whole or not at
/// all: a new file, synced, renamed over the old.
pub fn edit_toml(
    path: &Path,
    edit: impl FnOnce(&mut toml_edit::DocumentMut) -> Result<(), String>,
) -> Result<(), ConfigError> {
    let fail = |reason: String| ConfigError::Read {
        path: path.display().to_string(),
        reason,
    };
    let text = match std::fs::read_to_string(path) {
        Ok(text) => text,
        Err(e) if e.kind() == std::io::ErrorKind::NotFound => String::new(),
        Err(e) => return Err(fail(e.to_string())),
    };
    let mut doc: toml_edit::DocumentMut = text
        .parse()
        .map_err(|e| ConfigError::Parse(format!("{}: {e}", path.display())))?;
    edit(&mut doc).map_err(|e| ConfigError::Parse(format!("{}: {e}", path.display())))?;
    let dir = match path.parent() {
        Some(dir) if !dir.as_os_str().is_empty() => dir,
        _ => Path::new("."),
    };
    let written = |e: std::io::Error| ConfigError::Write {
        path: path.display().to_string(),
        reason: e.to_string(),
    };
    let mut file = tempfile::NamedTempFile::new_in(dir).map_err(written)?;
    std::io::Write::write_all(&mut file, doc.to_string().as_bytes())
        .and_then(|()| file.as_file().sync_all())
        .map_err(written)?;
    file.persist(path).map_err(|e| written(e.error))?;
    Ok(())
}

//! The security file every process reads (`--security PATH` or
//! `TWEEZER_SECURITY`): the certificates it serves and presents, the CA it
//! trusts, the tokens it accepts and the token it sends. Relative paths are
//! relative to the file's directory, so a directory of credentials moves
//! as one.

use crate::guarded_listener::ListenerLimits;
use crate::tokens::{Token, TokenError, Tokens};
use serde::{Deserialize, Serialize};
use std::path::{Path, PathBuf};

/// The environment variable that names the security file.
pub const SECURITY_ENV: &str = "TWEEZER_SECURITY";
/// The environment variable that holds a client's token (it overrides the
/// file's `token_file`).
pub const TOKEN_ENV: &str = "TWEEZER_TOKEN";

/// The file as written.
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct SecurityFile {
    /// No TLS: plain TCP, with a warning in the log. Tokens still apply.
    pub plaintext: bool,
    /// The CA certificate (PEM) that signed the services' certificates,
    /// and, with `require_client_cert`, the clients'.
    pub ca: Option<PathBuf>,
    /// This process's certificate (PEM): served by a service, presented by
    /// a client to a service that requires client certificates.
    pub cert: Option<PathBuf>,
    /// The certificate's private key (PEM).
    pub key: Option<PathBuf>,
    /// A service: refuse clients without a certificate signed by `ca`.
    pub require_client_cert: bool,
    /// A service: the tokens it accepts (`ROLE NAME sha256:HEX` lines).
    pub tokens: Option<PathBuf>,
    /// A client: the file holding its token (`TWEEZER_TOKEN` overrides).
    pub token_file: Option<PathBuf>,
    /// A service: how its listeners treat connections.
    pub listener: ListenerLimits,
}

/// A security file, read and its paths resolved.
#[derive(Clone, Debug)]
pub struct Security {
    /// Where it came from, for errors.
    pub source: String,
    file: SecurityFile,
}

/// What is wrong with the security settings.
#[derive(Debug, thiserror::Error)]
pub enum SecurityError {
    /// The file itself.
    #[error("security file {path}: {reason}")]
    File {
        /// The file.
        path: String,
        /// What is wrong.
        reason: String,
    },
    /// A field that is missing or contradicts another.
    #[error("security file {file}: `{field}` {reason}")]
    Field {
        /// The security file.
        file: String,
        /// The field.
        field: &'static str,
        /// What is wrong.
        reason: String,
    },
    /// A token or tokens file.
    #[error("{0}")]
    Token(#[from] TokenError),
    /// No security file was given.
    #[error(
        "no security file: pass --security PATH or set {SECURITY_ENV} (see docs/operations.md, Security; `tweezer cert issue --write-security FILE` and `tweezer token new --write-security FILE` write one)"
    )]
    Missing,
}

/// PEM files a TLS listener or client needs.
#[derive(Clone, Debug)]
pub struct Pem {
    /// The CA certificate.
    pub ca: Option<Vec<u8>>,
    /// This process's certificate and key.
    pub identity: Option<(Vec<u8>, Vec<u8>)>,
}

impl Security {
    /// The security file at `path`, or the one `TWEEZER_SECURITY` names.
    pub fn load(path: Option<&Path>) -> Result<Self, SecurityError> {
        let from_env = std::env::var_os(SECURITY_ENV).map(PathBuf::from);
        let path = path.map(Path::to_path_buf).or(from_env);
        let path = path.ok_or(SecurityError::Missing)?;
        let fail = |reason: String| SecurityError::File {
            path: path.display().to_string(),
            reason,
        };
        let text = std::fs::read_to_string(&path).map_err(|e| fail(e.to_string()))?;
        let file: SecurityFile = toml::from_str(&text).map_err(|e| fail(e.to_string()))?;
        let base = path.parent().unwrap_or(Path::new("."));
        Ok(Self::new(&path.display().to_string(), file, base))
    }

    /// Settings from `file`, its relative paths taken from `base`.
    pub fn new(source: &str, mut file: SecurityFile, base: &Path) -> Self {
        for path in [
            &mut file.ca,
            &mut file.cert,
            &mut file.key,
            &mut file.tokens,
            &mut file.token_file,
        ]
        .into_iter()
        .flatten()
        {
            if path.is_relative() {
                *path = base.join(&*path);
            }
        }
        Self {
            source: source.into(),
            file,
        }
    }

    /// The settings, paths resolved.
    pub fn file(&self) -> &SecurityFile {
        &self.file
    }

    /// Whether TLS is off.
    pub fn plaintext(&self) -> bool {
        self.file.plaintext
    }

    fn field(&self, field: &'static str, reason: String) -> SecurityError {
        SecurityError::Field {
            file: self.source.clone(),
            field,
            reason,
        }
    }

    /// A file that `field` names and that cannot be read or parsed, blamed
    /// on the field.
    fn named_file(&self, field: &'static str, e: TokenError) -> SecurityError {
        match e {
            TokenError::File { path, reason } => {
                self.field(field, format!("names {path}: {reason}"))
            }
            other => other.into(),
        }
    }

    fn read(&self, field: &'static str, path: &Option<PathBuf>) -> Result<Vec<u8>, SecurityError> {
        let path = path
            .as_ref()
            .ok_or_else(|| self.field(field, "is not set".into()))?;
        std::fs::read(path).map_err(|e| {
            self.field(
                field,
                format!("names {}, which cannot be read: {e}", path.display()),
            )
        })
    }

    /// The PEM a service serves with; None when plaintext.
    pub fn server_pem(&self) -> Result<Option<Pem>, SecurityError> {
        if self.file.plaintext {
            return Ok(None);
        }
        let identity = (
            self.read("cert", &self.file.cert)?,
            self.read("key", &self.file.key)?,
        );
        let ca = if self.file.require_client_cert {
            Some(self.read("ca", &self.file.ca)?)
        } else {
            None
        };
        Ok(Some(Pem {
            ca,
            identity: Some(identity),
        }))
    }

    /// The CA the security file names, if it names one.
    pub fn ca_pem(&self) -> Result<Option<Vec<u8>>, SecurityError> {
        match self.file.ca {
            Some(_) => self.read("ca", &self.file.ca).map(Some),
            None => Ok(None),
        }
    }

    /// The PEM a client connects with; None when plaintext.
    pub fn client_pem(&self) -> Result<Option<Pem>, SecurityError> {
        if self.file.plaintext {
            return Ok(None);
        }
        let ca = self.read("ca", &self.file.ca)?;
        let identity = match (&self.file.cert, &self.file.key) {
            (Some(_), Some(_)) => Some((
                self.read("cert", &self.file.cert)?,
                self.read("key", &self.file.key)?,
            )),
            (None, None) => None,
            _ => return Err(self.field("cert", "and `key` must be set together".into())),
        };
        Ok(Some(Pem {
            ca: Some(ca),
            identity,
        }))
    }

    /// The tokens a service accepts.
    pub fn tokens(&self) -> Result<Tokens, SecurityError> {
        let path = self.file.tokens.as_ref().ok_or_else(|| {
            self.field(
                "tokens",
                "is not set: a service needs the tokens it accepts (`tweezer token new` makes them)"
                    .into(),
            )
        })?;
        let tokens = Tokens::read(path).map_err(|e| self.named_file("tokens", e))?;
        if tokens.is_empty() {
            return Err(self.field(
                "tokens",
                format!("{} lists no token: nobody could call", path.display()),
            ));
        }
        Ok(tokens)
    }

    /// The token a client sends: `TWEEZER_TOKEN`, else `token_file`.
    pub fn token(&self) -> Result<Token, SecurityError> {
        if let Ok(text) = std::env::var(TOKEN_ENV)
            && !text.trim().is_empty()
        {
            return Token::parse(&text).map_err(|e| {
                SecurityError::Token(TokenError::File {
                    path: format!("${TOKEN_ENV}"),
                    reason: e.to_string(),
                })
            });
        }
        let path = self.file.token_file.as_ref().ok_or_else(|| {
            self.field(
                "token_file",
                format!("is not set and {TOKEN_ENV} is empty: a client needs a token"),
            )
        })?;
        Token::read(path).map_err(|e| self.named_file("token_file", e))
    }

    /// The file as TOML.
    pub fn to_toml(&self) -> String {
        toml::to_string(&self.file).expect("the security file is TOML-representable")
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn relative_paths_are_taken_from_the_files_directory() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("security.toml");
        std::fs::write(&path, "ca = \"ca.crt\"\ntokens = \"/etc/tokens\"\n").unwrap();
        let security = Security::load(Some(&path)).unwrap();
        assert_eq!(security.file().ca, Some(dir.path().join("ca.crt")));
        assert_eq!(security.file().tokens, Some(PathBuf::from("/etc/tokens")));
    }

    #[test]
    fn errors_name_the_file_and_the_field() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("security.toml");
        std::fs::write(&path, "certificate = \"x\"\n").unwrap();
        let err = Security::load(Some(&path)).unwrap_err().to_string();
        assert!(
            err.contains("security.toml") && err.contains("certificate"),
            "{err}"
        );
        std::fs::write(&path, "cert = \"missing.crt\"\nkey = \"k\"\n").unwrap();
        let security = Security::load(Some(&path)).unwrap();
        let err = security.server_pem().unwrap_err().to_string();
        assert!(
            err.contains("`cert`") && err.contains("missing.crt"),
            "{err}"
        );
        let err = security.tokens().unwrap_err().to_string();
        assert!(err.contains("`tokens` is not set"), "{err}");
        std::fs::write(&path, "ca = \"ca.crt\"\ncert = \"c\"\n").unwrap();
        let err = Security::load(Some(&path))
            .unwrap()
            .client_pem()
            .unwrap_err()
            .to_string();
        assert!(
            err.contains("`ca`") || err.contains("set together"),
            "{err}"
        );
    }
}

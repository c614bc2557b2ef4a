//! Bearer tokens and their roles. A service keeps only each token's SHA-256
//! (a leaked tokens file grants nothing) and compares digests in constant
//! time; a client holds the token itself, in a file or `TWEEZER_TOKEN`.

use crate::private_file::{append_private, create_private};
use sha2::{Digest, Sha256};
use std::fmt;
use std::path::Path;
use std::str::FromStr;
use subtle::ConstantTimeEq;

/// What a token may do.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash)]
pub enum Role {
    /// Status, snapshots, telemetry: nothing that changes state.
    Read,
    /// An actor: streams transitions, and may read.
    Actor,
    /// Anything that changes state, all motion on the hardware agent, and
    /// reading.
    Control,
}

impl Role {
    /// Every role, for listings and errors.
    pub const ALL: [Role; 3] = [Role::Read, Role::Actor, Role::Control];

    /// Whether a token of this role may make a call that needs `needed`.
    pub fn grants(self, needed: Role) -> bool {
        self == needed || needed == Role::Read
    }

    /// The role's name in token files and on the command line.
    pub fn name(self) -> &'static str {
        match self {
            Role::Read => "read",
            Role::Actor => "actor",
            Role::Control => "control",
        }
    }
}

impl fmt::Display for Role {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str(self.name())
    }
}

impl FromStr for Role {
    type Err = String;

    fn from_str(s: &str) -> Result<Self, Self::Err> {
        Role::ALL
            .into_iter()
            .find(|r| r.name() == s)
            .ok_or_else(|| format!("unknown role `{s}` (roles: read, actor, control)"))
    }
}

/// The prefix of every token: recognisable in a leaked paste, and by
/// secret scanners.
const PREFIX: &str = "tzr_";

/// A secret bearer token. Its `Debug` never shows the secret.
#[derive(Clone, PartialEq, Eq)]
pub struct Token(String);

impl Token {
    /// A new token: 32 bytes from the operating system's generator.
    pub fn generate() -> Result<Self, TokenError> {
        let mut bytes = [0u8; 32];
        getrandom::fill(&mut bytes).map_err(|e| TokenError::Random(e.to_string()))?;
        Ok(Self(format!("{PREFIX}{}", hex(&bytes))))
    }

    /// A token as a client presents it; the error says what is malformed
    /// without echoing the secret.
    pub fn parse(text: &str) -> Result<Self, TokenError> {
        let text = text.trim();
        if text.is_empty() {
            return Err(TokenError::Malformed("it is empty".into()));
        }
        if !text.bytes().all(|b| b.is_ascii_graphic()) {
            return Err(TokenError::Malformed(
                "it holds spaces or non-ASCII characters".into(),
            ));
        }
        Ok(Self(text.to_string()))
    }

    /// The token read from `path` (its first line).
    pub fn read(path: &Path) -> Result<Self, TokenError> {
        let text = std::fs::read_to_string(path).map_err(|e| TokenError::File {
            path: path.display().to_string(),
            reason: e.to_string(),
        })?;
        Self::parse(text.lines().next().unwrap_or("")).map_err(|e| TokenError::File {
            path: path.display().to_string(),
            reason: e.to_string(),
        })
    }

    /// The secret, for the `authorization` header only.
    pub fn secret(&self) -> &str {
        &self.0
    }

    /// The token's SHA-256, as a tokens file keeps it.
    pub fn digest(&self) -> [u8; 32] {
        Sha256::digest(self.0.as_bytes()).into()
    }

    /// Writes the token to `path`, readable by its owner only; refuses to
    /// overwrite a file.
    pub fn write_new(&self, path: &Path) -> Result<(), TokenError> {
        write_private(path, format!("{}\n", self.0).as_bytes(), false)
    }
}

impl fmt::Debug for Token {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str("Token(<secret>)")
    }
}

/// One accepted token: its role, a name for logs, and its digest.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct TokenEntry {
    /// What the token may do.
    pub role: Role,
    /// Whose it is (`alice`, `actor`, ...), logged with the calls it makes.
    pub name: String,
    digest: [u8; 32],
}

impl TokenEntry {
    /// The entry for `token`.
    pub fn new(role: Role, name: &str, token: &Token) -> Result<Self, TokenError> {
        check_name(name)?;
        Ok(Self {
            role,
            name: name.into(),
            digest: token.digest(),
        })
    }

    /// The entry as a line of a tokens file.
    pub fn line(&self) -> String {
        format!("{} {} sha256:{}", self.role, self.name, hex(&self.digest))
    }
}

/// The tokens a service accepts, as its tokens file lists them: one
/// `ROLE NAME sha256:HEX` per line, `#` comments.
#[derive(Clone, Debug, Default, PartialEq, Eq)]
pub struct Tokens {
    entries: Vec<TokenEntry>,
}

impl Tokens {
    /// The tokens listed in `text`; errors name the line.
    pub fn parse(text: &str) -> Result<Self, TokenError> {
        let mut entries = Vec::new();
        for (i, line) in text.lines().enumerate() {
            let line = line.trim();
            if line.is_empty() || line.starts_with('#') {
                continue;
            }
            let bad = |reason: String| TokenError::Line {
                line: i + 1,
                reason,
            };
            let fields: Vec<&str> = line.split_whitespace().collect();
            let [role, name, digest] = fields[..] else {
                return Err(bad(format!(
                    "expected `ROLE NAME sha256:HEX`, found {} fields",
                    fields.len()
                )));
            };
            let role = role.parse().map_err(bad)?;
            check_name(name).map_err(|e| bad(e.to_string()))?;
            let digest = digest
                .strip_prefix("sha256:")
                .and_then(unhex)
                .ok_or_else(|| bad("the digest is not `sha256:` and 64 hex digits".into()))?;
            entries.push(TokenEntry {
                role,
                name: name.into(),
                digest,
            });
        }
        Ok(Self { entries })
    }

    /// The tokens file at `path`.
    pub fn read(path: &Path) -> Result<Self, TokenError> {
        let text = std::fs::read_to_string(path).map_err(|e| TokenError::File {
            path: path.display().to_string(),
            reason: e.to_string(),
        })?;
        Self::parse(&text).map_err(|e| TokenError::File {
            path: path.display().to_string(),
            reason: e.to_string(),
        })
    }

    /// Appends `entry` to the tokens file at `path` (created readable by
    /// its owner only); refuses a name already listed.
    pub fn append(path: &Path, entry: &TokenEntry) -> Result<(), TokenError> {
        let existing = match std::fs::read_to_string(path) {
            Ok(text) => Self::parse(&text).map_err(|e| TokenError::File {
                path: path.display().to_string(),
                reason: e.to_string(),
            })?,
            Err(e) if e.kind() == std::io::ErrorKind::NotFound => Self::default(),
            Err(e) => {
                return Err(TokenError::File {
                    path: path.display().to_string(),
                    reason: e.to_string(),
                });
            }
        };
        if existing.entries.iter().any(|e| e.name == entry.name) {
            return Err(TokenError::File {
                path: path.display().to_string(),
                reason: format!("it already lists a token named `{}`", entry.name),
            });
        }
        write_private(path, format!("{}\n", entry.line()).as_bytes(), true)
    }

    /// How many tokens are accepted.
    pub fn len(&self) -> usize {
        self.entries.len()
    }

    /// Whether no token is accepted.
    pub fn is_empty(&self) -> bool {
        self.entries.is_empty()
    }

    /// Whether `entry`'s token is still listed with a role that grants
    /// `needed` (its digest compared in constant time).
    pub(crate) fn grants(&self, entry: &TokenEntry, needed: Role) -> bool {
        let mut granted = false;
        for listed in &self.entries {
            if bool::from(listed.digest.ct_eq(&entry.digest)) {
                granted = listed.role.grants(needed);
            }
        }
        granted
    }

    /// The entry `presented` matches, if any. Every entry's digest is
    /// compared, in constant time, whatever matches.
    pub fn verify(&self, presented: &str) -> Option<&TokenEntry> {
        let digest: [u8; 32] = Sha256::digest(presented.as_bytes()).into();
        let mut found = None;
        for entry in &self.entries {
            if bool::from(entry.digest.ct_eq(&digest)) {
                found = Some(entry);
            }
        }
        found
    }
}

/// What is wrong with a token, a tokens file or a token file.
#[derive(Debug, thiserror::Error)]
pub enum TokenError {
    /// The token text itself.
    #[error("malformed token: {0}")]
    Malformed(String),
    /// A line of a tokens file.
    #[error("line {line}: {reason}")]
    Line {
        /// 1-based.
        line: usize,
        /// What is wrong.
        reason: String,
    },
    /// A file that cannot be read, parsed or written.
    #[error("{path}: {reason}")]
    File {
        /// The file.
        path: String,
        /// What is wrong.
        reason: String,
    },
    /// A name that cannot go in a tokens file.
    #[error("token name `{0}`: use 1 to 64 letters, digits, `.`, `_` or `-`")]
    Name(String),
    /// The operating system's generator failed.
    #[error("cannot draw random bytes: {0}")]
    Random(String),
}

/// Whether `name` is 1 to 64 letters, digits, `.`, `_` or `-`: a name for
/// logs and tokens files, and a plain file name (no `/`).
pub(crate) fn is_plain_name(name: &str) -> bool {
    (1..=64).contains(&name.len())
        && name
            .bytes()
            .all(|b| b.is_ascii_alphanumeric() || b"._-".contains(&b))
}

fn check_name(name: &str) -> Result<(), TokenError> {
    if is_plain_name(name) {
        Ok(())
    } else {
        Err(TokenError::Name(name.into()))
    }
}

/// Writes (or appends) `bytes` to the private file `path`.
fn write_private(path: &Path, bytes: &[u8], append: bool) -> Result<(), TokenError> {
    let written = if append {
        append_private(path, bytes)
    } else {
        create_private(path, bytes)
    };
    written.map_err(|e| TokenError::File {
        path: path.display().to_string(),
        reason: e.to_string(),
    })
}

fn hex(bytes: &[u8]) -> String {
    bytes.iter().map(|b| format!("{b:02x}")).collect()
}

fn unhex(text: &str) -> Option<[u8; 32]> {
    if text.len() != 64 || !text.is_ascii() {
        return None;
    }
    let mut out = [0u8; 32];
    for (i, byte) in out.iter_mut().enumerate() {
        *byte = u8::from_str_radix(&text[2 * i..2 * i + 2], 16).ok()?;
    }
    Some(out)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_listed_token_verifies_with_its_role_and_others_do_not() {
        let read = Token::generate().unwrap();
        let control = Token::generate().unwrap();
        assert_ne!(read, control);
        assert!(read.secret().starts_with("tzr_") && read.secret().len() == 68);
        let text = format!(
            "# tokens\n{}\n\n{}\n",
            TokenEntry::new(Role::Read, "alice", &read).unwrap().line(),
            TokenEntry::new(Role::Control, "bob", &control)
                .unwrap()
                .line()
        );
        let tokens = Tokens::parse(&text).unwrap();
        assert_eq!(tokens.len(), 2);
        let alice = tokens.verify(read.secret()).unwrap();
        assert_eq!((alice.role, alice.name.as_str()), (Role::Read, "alice"));
        assert_eq!(tokens.verify(control.secret()).unwrap().role, Role::Control);
        assert!(tokens.verify("tzr_0000").is_none());
        assert!(tokens.verify("").is_none());
    }

    #[test]
    fn roles_grant_read_and_themselves_only() {
        assert!(Role::Control.grants(Role::Read) && Role::Control.grants(Role::Control));
        assert!(Role::Actor.grants(Role::Read) && Role::Actor.grants(Role::Actor));
        assert!(!Role::Actor.grants(Role::Control) && !Role::Control.grants(Role::Actor));
        assert!(!Role::Read.grants(Role::Control) && !Role::Read.grants(Role::Actor));
        assert_eq!("control".parse::<Role>(), Ok(Role::Control));
        assert!("admin".parse::<Role>().unwrap_err().contains("admin"));
    }

    #[test]
    fn malformed_tokens_files_name_the_line() {
        let bad = [
            ("read alice", "found 2 fields"),
            ("admin alice sha256:00", "unknown role `admin`"),
            ("read al!ce sha256:00", "token name"),
            ("read alice sha1:00", "64 hex digits"),
        ];
        for (line, expected) in bad {
            let err = Tokens::parse(&format!("# header\n{line}\n"))
                .unwrap_err()
                .to_string();
            assert!(
                err.starts_with("line 2:") && err.contains(expected),
                "{line}: {err}"
            );
        }
    }

    #[test]
    fn debug_never_shows_the_secret() {
        let token = Token::generate().unwrap();
        assert!(!format!("{token:?}").contains(token.secret()));
        assert!(Token::parse(" \n").is_err());
        assert!(Token::parse("a b").is_err());
    }

    #[test]
    fn token_files_are_private_and_never_overwritten() {
        let dir = tempfile::tempdir().unwrap();
        let token = Token::generate().unwrap();
        let path = dir.path().join("alice.token");
        token.write_new(&path).unwrap();
        assert!(token.write_new(&path).is_err());
        assert_eq!(Token::read(&path).unwrap(), token);
        #[cfg(unix)]
        {
            use std::os::unix::fs::PermissionsExt;
            let mode = std::fs::metadata(&path).unwrap().permissions().mode();
            assert_eq!(mode & 0o777, 0o600);
        }
        let tokens = dir.path().join("tokens");
        let entry = TokenEntry::new(Role::Read, "alice", &token).unwrap();
        Tokens::append(&tokens, &entry).unwrap();
        let err = Tokens::append(&tokens, &entry).unwrap_err().to_string();
        assert!(err.contains("already lists a token named `alice`"), "{err}");
        assert!(
            Tokens::read(&tokens)
                .unwrap()
                .verify(token.secret())
                .is_some()
        );
    }
}

//! Credentials for processes that talk over loopback on one machine (a
//! training run, a benchmark): a CA, the learner's loopback certificate,
//! and a token each for the actors, for reading and for control, with a
//! security file for each process. Made once in a directory and reused
//! after. The CA's key is not kept: nothing else can be issued under it.

use crate::certs::{issue, new_ca};
use crate::{Role, SecurityFile, Token, TokenEntry, Tokens, create_private};
use anyhow::Context;
use std::path::{Path, PathBuf};

/// How long the certificates are valid.
const DAYS: u32 = 3650;

/// The security files of a loopback deployment's processes.
#[derive(Clone, Debug)]
pub struct LoopbackCredentials {
    /// The learner's (certificate, key, tokens).
    pub learner: PathBuf,
    /// The actors' (CA, actor token).
    pub actor: PathBuf,
    /// An operator's, to read (CA, read token).
    pub read: PathBuf,
    /// An operator's, to control (CA, control token).
    pub control: PathBuf,
}

impl LoopbackCredentials {
    fn at(dir: &Path) -> Self {
        Self {
            learner: dir.join("learner.toml"),
            actor: dir.join("actor.toml"),
            read: dir.join("read.toml"),
            control: dir.join("control.toml"),
        }
    }

    /// The credentials in `dir`, made first if it has none.
    pub fn provision(dir: &Path) -> anyhow::Result<Self> {
        let credentials = Self::at(dir);
        if credentials.learner.exists() {
            return Ok(credentials);
        }
        std::fs::create_dir_all(dir).with_context(|| format!("cannot create {}", dir.display()))?;
        let ca = new_ca("tweezer-rl run CA", DAYS)?;
        let learner = issue(
            &ca,
            "learner",
            &["127.0.0.1".into(), "localhost".into()],
            DAYS,
        )?;
        write(&dir.join("ca.crt"), &ca.cert_pem)?;
        write(&dir.join("learner.crt"), &learner.cert_pem)?;
        write(&dir.join("learner.key"), &learner.key_pem)?;
        let tokens = dir.join("tokens");
        for role in Role::ALL {
            let token = Token::generate()?;
            token.write_new(&dir.join(format!("{role}.token")))?;
            Tokens::append(&tokens, &TokenEntry::new(role, role.name(), &token)?)?;
        }
        let server = SecurityFile {
            cert: Some("learner.crt".into()),
            key: Some("learner.key".into()),
            tokens: Some("tokens".into()),
            ..SecurityFile::default()
        };
        write_toml(&credentials.learner, &server)?;
        for (path, role) in [
            (&credentials.actor, Role::Actor),
            (&credentials.read, Role::Read),
            (&credentials.control, Role::Control),
        ] {
            let client = SecurityFile {
                ca: Some("ca.crt".into()),
                token_file: Some(format!("{role}.token").into()),
                ..SecurityFile::default()
            };
            write_toml(path, &client)?;
        }
        Ok(credentials)
    }
}

/// Writes a new file readable by its owner only.
fn write(path: &Path, text: &str) -> anyhow::Result<()> {
    create_private(path, text.as_bytes())
        .with_context(|| format!("cannot write {}", path.display()))
}

fn write_toml(path: &Path, file: &SecurityFile) -> anyhow::Result<()> {
    write(path, &toml::to_string(file)?)
}

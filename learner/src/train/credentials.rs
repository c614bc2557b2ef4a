//! The run's own credentials, made when a run starts: a CA, the learner's
//! loopback certificate, and a token each for the actors, for reading and
//! for control, with a security file for each process (`security/`). A
//! resumed run uses those it has. The CA's key is not kept: nothing else
//! can be issued under it.

use anyhow::Context;
use std::path::{Path, PathBuf};
use tweezer_rpc::certs::{issue, new_ca};
use tweezer_rpc::{Role, SecurityFile, Token, TokenEntry, Tokens, create_private};

/// The run directory's credentials.
pub const SECURITY_DIR: &str = "security";
/// How long the run's certificates are valid.
const DAYS: u32 = 3650;

/// The security files of the run's processes.
pub struct Credentials {
    /// The learner's (certificate, key, tokens).
    pub learner: PathBuf,
    /// The actors' (CA, actor token).
    pub actor: PathBuf,
    /// An operator's, to read (CA, read token).
    pub read: PathBuf,
    /// An operator's, to control (CA, control token).
    pub control: PathBuf,
}

impl Credentials {
    fn at(dir: &Path) -> Self {
        Self {
            learner: dir.join("learner.toml"),
            actor: dir.join("actor.toml"),
            read: dir.join("read.toml"),
            control: dir.join("control.toml"),
        }
    }

    /// The credentials in `run_dir`, made first if it has none.
    pub fn provision(run_dir: &Path) -> anyhow::Result<Self> {
        let dir = run_dir.join(SECURITY_DIR);
        let credentials = Self::at(&dir);
        if credentials.learner.exists() {
            return Ok(credentials);
        }
        std::fs::create_dir_all(&dir)
            .with_context(|| format!("cannot create {}", dir.display()))?;
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

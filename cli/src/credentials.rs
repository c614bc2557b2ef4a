//! `tweezer cert ...` and `tweezer token ...`: the deployment's CA, each
//! process's certificate, and bearer tokens. Secrets go to files created
//! readable by their owner only, never to the terminal.

use crate::{CertCommand, TokenCommand};
use anyhow::{Context, bail};
use std::path::Path;
use tweezer_rpc::certs::{Issued, issue, new_ca};
use tweezer_rpc::{Token, TokenEntry, Tokens, create_private};

/// Runs a `cert` command.
pub fn cert(command: CertCommand) -> anyhow::Result<()> {
    match command {
        CertCommand::Ca { out, name, days } => {
            let ca = new_ca(&name, days)?;
            std::fs::create_dir_all(&out)
                .with_context(|| format!("cannot create {}", out.display()))?;
            write_pair(&out, "ca", &ca)?;
            println!(
                "wrote {0}/ca.crt (give it to every process) and {0}/ca.key (keep it offline)",
                out.display()
            );
        }
        CertCommand::Issue {
            ca,
            name,
            hosts,
            out,
            days,
        } => {
            let read = |file: &str| {
                let path = ca.join(file);
                std::fs::read_to_string(&path)
                    .with_context(|| format!("cannot read the CA's {}", path.display()))
            };
            let authority = Issued {
                cert_pem: read("ca.crt")?,
                key_pem: read("ca.key")?,
            };
            if hosts.is_empty() {
                bail!("give the host names or addresses clients use: --host learner.example.org");
            }
            let issued = issue(&authority, &name, &hosts, days)?;
            std::fs::create_dir_all(&out)
                .with_context(|| format!("cannot create {}", out.display()))?;
            write_pair(&out, &name, &issued)?;
            println!(
                "wrote {0}/{name}.crt and {0}/{name}.key for {1}",
                out.display(),
                hosts.join(", ")
            );
        }
    }
    Ok(())
}

/// Runs a `token` command.
pub fn token(command: TokenCommand) -> anyhow::Result<()> {
    match command {
        TokenCommand::New {
            role,
            name,
            tokens,
            out,
        } => {
            let role = role
                .parse::<tweezer_rpc::Role>()
                .map_err(anyhow::Error::msg)?;
            let token = Token::generate()?;
            let entry = TokenEntry::new(role, &name, &token)?;
            token.write_new(&out)?;
            if let Err(e) = Tokens::append(&tokens, &entry) {
                let _ = std::fs::remove_file(&out);
                return Err(e.into());
            }
            println!(
                "wrote the {role} token `{name}` to {} and its digest to {}",
                out.display(),
                tokens.display()
            );
        }
    }
    Ok(())
}

/// Writes `<name>.crt` and `<name>.key` into `dir`, refusing to overwrite.
fn write_pair(dir: &Path, name: &str, issued: &Issued) -> anyhow::Result<()> {
    let cert = dir.join(format!("{name}.crt"));
    let key = dir.join(format!("{name}.key"));
    for path in [&cert, &key] {
        if path.exists() {
            bail!(
                "{} exists: remove it first, or choose another --out",
                path.display()
            );
        }
    }
    create_private(&key, issued.key_pem.as_bytes())
        .with_context(|| format!("cannot write {}", key.display()))?;
    std::fs::write(&cert, &issued.cert_pem)
        .with_context(|| format!("cannot write {}", cert.display()))
}

//! `tweezer cert ...` and `tweezer token ...`: the deployment's CA, each
//! process's certificate, and bearer tokens, and the security files that
//! name them. Secrets go to files created readable by their owner only,
//! never to the terminal.

use crate::{CertCommand, TokenCommand};
use anyhow::{Context, bail};
use std::path::Path;
use tweezer_rpc::certs::{Issued, issue, new_ca};
use tweezer_rpc::{SecurityFile, Token, TokenEntry, Tokens, create_private};

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
            write_security,
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
            if let Some(security) = write_security {
                let cert = out.join(format!("{name}.crt"));
                let key = out.join(format!("{name}.key"));
                let ca = ca.join("ca.crt");
                set_paths(&security, &[("ca", &ca), ("cert", &cert), ("key", &key)])?;
            }
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
            write_security,
            ca,
            accepted_by,
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
            if let Some(security) = write_security {
                let ca = ca.map(|dir| dir.join("ca.crt"));
                let mut fields = vec![("token_file", out.as_path())];
                fields.extend(ca.as_deref().map(|ca| ("ca", ca)));
                set_paths(&security, &fields)?;
            }
            for service in accepted_by {
                set_paths(&service, &[("tokens", &tokens)])?;
            }
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

/// Sets path fields of the security file at `security` (created if absent,
/// every other line kept) and says so. A file in the security file's own
/// directory is written by name, so the directory moves as one; any other
/// as an absolute path. The result must still read as a security file.
fn set_paths(security: &Path, fields: &[(&str, &Path)]) -> anyhow::Result<()> {
    let written: Vec<(&str, String)> = fields
        .iter()
        .map(|(field, file)| Ok((*field, as_written(security, file)?)))
        .collect::<anyhow::Result<_>>()?;
    tweezer_config::edit_toml(security, |doc| {
        for (field, path) in &written {
            doc[field] = toml_edit::value(path.as_str());
        }
        toml::from_str::<SecurityFile>(&doc.to_string())
            .map(drop)
            .map_err(|e| format!("not a security file: {e}"))
    })?;
    let lines: Vec<String> = written
        .iter()
        .map(|(field, path)| format!("{field} = \"{path}\""))
        .collect();
    println!("set {} in {}", lines.join(", "), security.display());
    Ok(())
}

/// How `file` is named in the security file at `security`.
fn as_written(security: &Path, file: &Path) -> anyhow::Result<String> {
    let dir = |path: &Path| {
        let dir = path.parent().filter(|d| !d.as_os_str().is_empty());
        dir.unwrap_or(Path::new(".")).canonicalize().ok()
    };
    if let (Some(a), Some(b), Some(name)) = (dir(security), dir(file), file.file_name())
        && a == b
    {
        return Ok(name.to_string_lossy().into_owned());
    }
    let absolute =
        std::path::absolute(file).with_context(|| format!("cannot resolve {}", file.display()))?;
    Ok(absolute.display().to_string())
}

//! Files that hold secrets (tokens, private keys): created readable and
//! writable by their owner only, and synced before success is reported.

use std::io::Write;
use std::path::Path;

/// Writes `bytes` to a new file at `path`; refuses to overwrite one.
pub fn create_private(path: &Path, bytes: &[u8]) -> std::io::Result<()> {
    write(path, bytes, false).map_err(|e| match e.kind() {
        std::io::ErrorKind::AlreadyExists => std::io::Error::new(
            e.kind(),
            "the file already exists, and a secret is never overwritten: remove it first, or choose another path",
        ),
        _ => e,
    })
}

/// Appends `bytes` to the file at `path`, creating it if need be.
pub fn append_private(path: &Path, bytes: &[u8]) -> std::io::Result<()> {
    write(path, bytes, true)
}

fn write(path: &Path, bytes: &[u8], append: bool) -> std::io::Result<()> {
    let mut options = std::fs::OpenOptions::new();
    if append {
        options.append(true).create(true);
    } else {
        options.write(true).create_new(true);
    }
    #[cfg(unix)]
    std::os::unix::fs::OpenOptionsExt::mode(&mut options, 0o600);
    let mut file = options.open(path)?;
    file.write_all(bytes)?;
    file.sync_all()
}

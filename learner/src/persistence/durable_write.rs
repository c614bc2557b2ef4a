//! Durable file writes: a file is either wholly the old one or wholly the
//! new one after a crash, never a mix.

use std::fs::{self, File};
use std::io::{self, Write};
use std::path::{Path, PathBuf};

/// Writes `path` atomically: a temporary file in the same directory is
/// written and fsynced, renamed over `path`, and the directory fsynced so
/// the rename itself survives a crash.
pub fn write_atomic(
    path: &Path,
    write: impl FnOnce(&mut dyn Write) -> io::Result<()>,
) -> io::Result<()> {
    let (dir, tmp) = beside(path, TMP)?;
    let result = (|| {
        let mut file = io::BufWriter::with_capacity(1 << 20, File::create(&tmp)?);
        write(&mut file)?;
        let file = file.into_inner().map_err(io::IntoInnerError::into_error)?;
        file.sync_all()?;
        fs::rename(&tmp, path)?;
        sync_dir(&dir)
    })();
    if result.is_err() {
        let _ = fs::remove_file(&tmp);
    }
    result
}

/// Writes the whole of `bytes` to `path` atomically (see [`write_atomic`]).
pub fn write_bytes_atomic(path: &Path, bytes: &[u8]) -> io::Result<()> {
    write_atomic(path, |w| w.write_all(bytes))
}

/// Makes `to` another name for the file `from`, atomically replacing what
/// `to` named before (a hard link, renamed into place).
pub fn link_atomic(from: &Path, to: &Path) -> io::Result<()> {
    let (dir, tmp) = beside(to, LINK)?;
    let _ = fs::remove_file(&tmp);
    fs::hard_link(from, &tmp)?;
    fs::rename(&tmp, to).inspect_err(|_| {
        let _ = fs::remove_file(&tmp);
    })?;
    sync_dir(&dir)
}

/// The suffixes of the temporary names [`beside`] gives.
const TMP: &str = "tmp";
const LINK: &str = "link";

/// Removes the temporary files that writes interrupted by a crash left in
/// `dir` (a SIGKILL mid-checkpoint leaves one as large as what was
/// written); returns their paths. Call it only while no write is under
/// way: with the run directory locked, before anything writes.
pub fn remove_leftovers(dir: &Path) -> io::Result<Vec<PathBuf>> {
    let mut removed = Vec::new();
    let entries = match fs::read_dir(dir) {
        Ok(entries) => entries,
        Err(e) if e.kind() == io::ErrorKind::NotFound => return Ok(removed),
        Err(e) => return Err(e),
    };
    for entry in entries {
        let path = entry?.path();
        let name = path.file_name().map(|n| n.to_string_lossy().into_owned());
        let leftover = name.is_some_and(|name| {
            name.starts_with('.')
                && [TMP, LINK]
                    .iter()
                    .any(|suffix| name.ends_with(&format!(".{suffix}")))
        });
        if leftover && path.is_file() {
            fs::remove_file(&path)?;
            removed.push(path);
        }
    }
    Ok(removed)
}

/// The directory of `path` and a hidden temporary name beside it.
fn beside(path: &Path, suffix: &str) -> io::Result<(PathBuf, PathBuf)> {
    let dir = path.parent().unwrap_or(Path::new(".")).to_path_buf();
    let name = path
        .file_name()
        .ok_or_else(|| io::Error::new(io::ErrorKind::InvalidInput, "path has no file name"))?;
    let tmp = dir.join(format!(".{}.{suffix}", name.to_string_lossy()));
    Ok((dir, tmp))
}

/// Fsyncs a directory, making renames and deletions in it durable.
pub fn sync_dir(dir: &Path) -> io::Result<()> {
    File::open(dir)?.sync_all()
}

//! Outputs written whole or not at all: every file goes to a temporary name beside its final
//! one, is flushed to the disk (`fsync`), and is renamed into place, so a process killed at any
//! instant (or a camera losing power) leaves the old file or none, never a partial one. A
//! directory of files that belong together (a plan, a model, a recording) has one file that
//! commits it, its manifest: the old manifest is removed before any file is replaced and the
//! new one is renamed last, so a reader finds the old set, no manifest, or the new set.

use std::fs::File;
use std::io::Write;
use std::path::{Path, PathBuf};

use crate::{Error, Result};

/// The temporary name `path` is written under before it is renamed into place
/// (`.<name>.tmp-<pid>` in the same folder, so the rename never crosses file systems).
pub fn temporary_path(path: &Path) -> PathBuf {
    let name = path.file_name().map(|n| n.to_string_lossy().into_owned()).unwrap_or_default();
    path.with_file_name(format!(".{name}.tmp-{}", std::process::id()))
}

/// The folder `path` is in (`.` for a bare file name).
fn folder(path: &Path) -> &Path {
    path.parent().filter(|d| !d.as_os_str().is_empty()).unwrap_or(Path::new("."))
}

fn io(path: &Path) -> impl Fn(std::io::Error) -> Error + '_ {
    move |err| Error::Io { path: path.to_path_buf(), err }
}

/// Write `bytes` to `tmp` and flush them to the disk; `path` (the final name) names errors.
fn write_flushed(tmp: &Path, path: &Path, bytes: &[u8]) -> Result<()> {
    let written = File::create(tmp).and_then(|mut f| {
        f.write_all(bytes)?;
        f.sync_all()
    });
    written.map_err(|e| {
        let _ = std::fs::remove_file(tmp);
        io(path)(e)
    })
}

/// Flush a folder's entries (the renames in it) to the disk. Best effort: some file systems
/// cannot open a folder for this, and the data itself is flushed already.
fn sync_folder(dir: &Path) {
    if let Ok(d) = File::open(dir) {
        let _ = d.sync_all();
    }
}

/// Write `bytes` to `path` whole or not at all: a temporary file beside it, flushed, then
/// renamed over it. On an error nothing is left under either name and the old file, if any,
/// is untouched.
pub fn write_atomically(path: &Path, bytes: &[u8]) -> Result<()> {
    if path.file_name().is_none() {
        return Err(io(path)(std::io::Error::new(std::io::ErrorKind::InvalidInput, "not a file path")));
    }
    let tmp = temporary_path(path);
    write_flushed(&tmp, path, bytes)?;
    commit(&tmp, path)
}

/// Put the finished temporary file `tmp` (written by someone else, such as FFmpeg) in place as
/// `path`: flushed, renamed, the folder flushed. On an error `tmp` is removed.
pub fn commit(tmp: &Path, path: &Path) -> Result<()> {
    let done = File::open(tmp).and_then(|f| f.sync_all()).and_then(|()| std::fs::rename(tmp, path));
    if let Err(e) = done {
        let _ = std::fs::remove_file(tmp);
        return Err(io(path)(e));
    }
    sync_folder(folder(path));
    Ok(())
}

/// Write the files of one set into `dir` (created if absent), `manifest` among them: every
/// file is written and flushed under its temporary name first (an error there leaves the old
/// set as it was); then the old manifest is removed, the other files are renamed into place,
/// and the manifest last.
pub fn write_files_atomically(dir: &Path, files: &[(&str, &[u8])], manifest: &str) -> Result<()> {
    std::fs::create_dir_all(dir).map_err(io(dir))?;
    let temporaries: Vec<(PathBuf, PathBuf)> =
        files.iter().map(|(name, _)| (temporary_path(&dir.join(name)), dir.join(name))).collect();
    let remove_all = || temporaries.iter().for_each(|(tmp, _)| drop(std::fs::remove_file(tmp)));
    for ((tmp, path), (_, bytes)) in temporaries.iter().zip(files) {
        if let Err(e) = write_flushed(tmp, path, bytes) {
            remove_all();
            return Err(e);
        }
    }
    let commit_path = dir.join(manifest);
    match std::fs::remove_file(&commit_path) {
        Err(e) if e.kind() != std::io::ErrorKind::NotFound => {
            remove_all();
            return Err(io(&commit_path)(e));
        }
        _ => sync_folder(dir),
    }
    let (last, rest): (Vec<_>, Vec<_>) = temporaries.iter().partition(|(_, path)| *path == commit_path);
    for (tmp, path) in rest.into_iter().chain(last) {
        if let Err(e) = std::fs::rename(tmp, path) {
            remove_all();
            return Err(io(path)(e));
        }
    }
    sync_folder(dir);
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_file_replaces_the_old_one_or_leaves_it() {
        let d = tempfile::tempdir().unwrap();
        let p = d.path().join("r.txt");
        write_atomically(&p, b"old").unwrap();
        write_atomically(&p, b"new").unwrap();
        assert_eq!(std::fs::read(&p).unwrap(), b"new");
        // A folder where the file should be: the rename fails, the temporary is gone.
        let q = d.path().join("sub");
        std::fs::create_dir_all(q.join("x")).unwrap();
        assert!(write_atomically(&q, b"x").is_err());
        assert_eq!(std::fs::read_dir(d.path()).unwrap().count(), 2, "no temporary left");
        assert!(write_atomically(Path::new("/"), b"x").is_err());
    }

    #[test]
    fn a_set_is_committed_by_its_manifest() {
        let d = tempfile::tempdir().unwrap();
        let dir = d.path().join("plan");
        write_files_atomically(&dir, &[("plan.json", b"m1"), ("a", b"a1"), ("b", b"b1")], "plan.json").unwrap();
        write_files_atomically(&dir, &[("plan.json", b"m2"), ("a", b"a2"), ("b", b"b2")], "plan.json").unwrap();
        let read = |n: &str| std::fs::read(dir.join(n)).unwrap();
        assert_eq!((read("plan.json"), read("a"), read("b")), (b"m2".to_vec(), b"a2".to_vec(), b"b2".to_vec()));
        // A file that cannot be written (a folder where its temporary goes): the old set stays
        // whole.
        let other = d.path().join("other");
        std::fs::create_dir_all(temporary_path(&other.join("b"))).unwrap();
        write_files_atomically(&other, &[("m", b"m1")], "m").unwrap();
        assert!(write_files_atomically(&other, &[("m", b"m2"), ("b", b"b")], "m").is_err());
        assert_eq!(std::fs::read(other.join("m")).unwrap(), b"m1");
        let names: Vec<_> = std::fs::read_dir(&other).unwrap().map(|e| e.unwrap().file_name()).collect();
        assert_eq!(names.len(), 2, "{names:?}");
    }
}

//! All-or-nothing file output: a file is written completely or not at all,
//! and a run's directory receives all of its files or none. And input
//! files read whole, up to a bound.

use crate::error::{Context, Result};
use crate::{bail, err};
use std::io::Write;
use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicU64, Ordering};

/// The most an input file (a model, data, barrier, prior-mean or sweep
/// file) may hold: 1 GiB. A larger one, or an endless stream such as
/// `/dev/zero`, is refused rather than read into memory without end.
pub const MAX_INPUT_BYTES: u64 = 1 << 30;

/// Reads an input file whole, up to [`MAX_INPUT_BYTES`].
pub fn read_input(path: &Path) -> std::io::Result<Vec<u8>> {
    read_bounded(path, MAX_INPUT_BYTES)
}

/// Reads `path` whole if it holds at most `limit` bytes.
fn read_bounded(path: &Path, limit: u64) -> std::io::Result<Vec<u8>> {
    use std::io::Read;
    let mut bytes = Vec::new();
    std::fs::File::open(path)?
        .take(limit + 1)
        .read_to_end(&mut bytes)?;
    if bytes.len() as u64 > limit {
        return Err(std::io::Error::new(
            std::io::ErrorKind::InvalidData,
            format!("it holds more than {limit} bytes, the most an input file may hold"),
        ));
    }
    Ok(bytes)
}

/// [`read_input`] as UTF-8 text.
pub fn read_input_text(path: &Path) -> std::io::Result<String> {
    String::from_utf8(read_input(path)?).map_err(|e| {
        std::io::Error::new(
            std::io::ErrorKind::InvalidData,
            format!("it is not UTF-8 text: {e}"),
        )
    })
}

/// Where the bytes meant for a path go.
enum Destination {
    /// A regular file, or none yet: a temporary sibling renamed over it.
    Replace(PathBuf),
    /// A FIFO, a terminal, another device or a descriptor of this process
    /// (`/dev/…`, `/proc/…`): appended to in place, as a rename would put a
    /// regular file in its stead (and replace a file the shell redirected
    /// a descriptor to).
    Stream(PathBuf),
    /// This process's own standard output (`/dev/stdout`, `/dev/fd/1`,
    /// `/proc/self/fd/1`): written to the descriptor itself, at its offset.
    Stdout,
    /// This process's own standard error, likewise.
    Stderr,
}

/// Says how the file at `path` is written, through symbolic links (the
/// link stays, its file is written).
fn destination(path: &Path) -> Result<Destination> {
    let text = path.to_string_lossy();
    match text.as_ref() {
        "/dev/stdout" | "/dev/fd/1" | "/proc/self/fd/1" => return Ok(Destination::Stdout),
        "/dev/stderr" | "/dev/fd/2" | "/proc/self/fd/2" => return Ok(Destination::Stderr),
        t if t.starts_with("/dev/") || t.starts_with("/proc/") => {
            return Ok(Destination::Stream(path.to_path_buf()))
        }
        _ => {}
    }
    match std::fs::metadata(path) {
        Ok(m) if m.is_dir() => Err(err!("output path '{}' is a directory", path.display())),
        Ok(m) if m.is_file() => Ok(Destination::Replace(
            std::fs::canonicalize(path)
                .with_context(|| format!("cannot resolve '{}'", path.display()))?,
        )),
        Ok(_) => Ok(Destination::Stream(path.to_path_buf())),
        // missing, or a link to a missing file: the link's file is created
        Err(_) => {
            let mut p = path.to_path_buf();
            for _ in 0..40 {
                match std::fs::read_link(&p) {
                    Ok(target) => {
                        p = match p.parent() {
                            Some(dir) => dir.join(target),
                            None => target,
                        }
                    }
                    Err(_) => return Ok(Destination::Replace(p)),
                }
            }
            Err(err!(
                "output path '{}': too many levels of symbolic links",
                path.display()
            ))
        }
    }
}

/// The directory `path` lies in: `.` for a bare name.
fn parent_dir(path: &Path) -> &Path {
    match path.parent() {
        Some(d) if !d.as_os_str().is_empty() => d,
        _ => Path::new("."),
    }
}

/// A temporary sibling of `path`, keeping its extension (plotters picks the
/// image format from it); the directory is created if missing.
fn temp_sibling(path: &Path) -> Result<PathBuf> {
    static COUNTER: AtomicU64 = AtomicU64::new(0);
    let name = path
        .file_name()
        .ok_or_else(|| err!("output path '{}' has no file name", path.display()))?;
    let dir = parent_dir(path).to_path_buf();
    if let Some(file) = dir.ancestors().find(|a| a.is_file()) {
        bail!(
            "cannot create output directory '{}': '{}' is a file, not a directory",
            dir.display(),
            file.display()
        );
    }
    std::fs::create_dir_all(&dir)
        .with_context(|| format!("cannot create output directory '{}'", dir.display()))?;
    let ext = path
        .extension()
        .map(|e| format!(".{}", e.to_string_lossy()))
        .unwrap_or_default();
    Ok(dir.join(format!(
        ".{}.tmp-{}-{}{ext}",
        name.to_string_lossy(),
        std::process::id(),
        COUNTER.fetch_add(1, Ordering::Relaxed)
    )))
}

/// Runs `write(tmp)`, which writes a temporary file, and moves its bytes to
/// `path`: renamed over a regular file (or a new one),
/// through symbolic links to their file; appended to a FIFO, a device or
/// this process's stdout or stderr. A failed write leaves `path` as it
/// was.
pub fn write_via_temp(path: &Path, write: impl FnOnce(&Path) -> Result<()>) -> Result<()> {
    let dest = destination(path)?;
    let tmp = match &dest {
        Destination::Replace(file) => temp_sibling(file)?,
        _ => temp_sibling(&std::env::temp_dir().join(path.file_name().unwrap_or_default()))?,
    };
    let result = write(&tmp).and_then(|()| {
        deliver(&tmp, &dest)
            .with_context(|| format!("cannot write output file '{}'", path.display()))
    });
    // gone after a rename; a temporary copy source otherwise
    let _ = std::fs::remove_file(&tmp);
    result
}

/// Moves the bytes of the temporary file `tmp` to `dest`.
fn deliver(tmp: &Path, dest: &Destination) -> std::io::Result<()> {
    let append = |to: &mut dyn Write| -> std::io::Result<()> {
        std::io::copy(&mut std::fs::File::open(tmp)?, to)?;
        to.flush()
    };
    match dest {
        Destination::Replace(file) => std::fs::rename(tmp, file),
        Destination::Stream(file) => {
            append(&mut std::fs::OpenOptions::new().append(true).open(file)?)
        }
        Destination::Stdout => append(&mut std::io::stdout().lock()),
        Destination::Stderr => append(&mut std::io::stderr().lock()),
    }
}

/// Copies the file `from` to `to` completely or not at all
/// ([`write_via_temp`]).
fn copy_to(from: &Path, to: &Path) -> Result<()> {
    write_via_temp(to, |tmp| {
        std::fs::copy(from, tmp)
            .map(|_| ())
            .with_context(|| format!("cannot write output file '{}'", to.display()))
    })
}

/// Writes `contents` to `path` completely or not at all (see
/// [`write_via_temp`]). Missing parent directories are created.
pub fn write_atomic(path: &Path, contents: &[u8]) -> Result<()> {
    write_via_temp(path, |tmp| {
        (|| -> std::io::Result<()> {
            let mut f = std::fs::File::create(tmp)?;
            f.write_all(contents)?;
            f.sync_all()
        })()
        .with_context(|| format!("cannot write output file '{}'", path.display()))
    })
}

/// Writes `value` as pretty JSON (and a final newline) to `path`,
/// completely or not at all.
pub fn write_json<T: serde::Serialize + ?Sized>(path: &Path, value: &T) -> Result<()> {
    let mut text = serde_json::to_string_pretty(value)?;
    text.push('\n');
    write_atomic(path, text.as_bytes())
}

/// An output directory filled all at once: files are written into a hidden
/// staging directory ([`path`](Self::path)), and
/// [`publish`](Self::publish) moves them into place. Dropped unpublished
/// (an error on the way), the staging directory is removed and the output
/// directory is left as it was. The staging directory lies inside an
/// existing output directory, else next to it, so that moves are renames
/// within one file system; a file that cannot be renamed into place (a
/// link, a FIFO, another file system below) is copied there.
#[derive(Debug)]
pub struct StagedDir {
    stage: PathBuf,
    out: PathBuf,
    /// Keep the staging directory when dropped (a failed publish).
    keep: bool,
}

impl StagedDir {
    /// Stages the files of the output directory `out`. Errors if `out`
    /// exists and is not a directory, is a link to a missing directory, or
    /// cannot be written (or created). Staging directories that earlier,
    /// interrupted runs left there are removed.
    pub fn new(out: &Path) -> Result<Self> {
        // a first run to `out` stages beside it, later ones inside it
        let name = out.file_name().unwrap_or_default().to_string_lossy();
        let parent = parent_dir(out);
        if parent.is_dir() {
            remove_stale(parent, &format!(".{name}.tmp-"));
        }
        let stage = if out.is_dir() {
            remove_stale(out, ".staging.tmp-");
            temp_sibling(&out.join("staging"))?
        } else if out.exists() {
            return Err(err!(
                "output directory '{}' exists and is not a directory",
                out.display()
            ));
        } else if std::fs::symlink_metadata(out).is_ok() {
            return Err(err!(
                "output directory '{}' is a symbolic link to a missing directory",
                out.display()
            ));
        } else {
            temp_sibling(out)?
        };
        std::fs::create_dir(&stage)
            .with_context(|| format!("cannot write into '{}'", out.display()))?;
        Ok(Self {
            stage,
            out: out.to_path_buf(),
            keep: false,
        })
    }

    /// The staging directory: write the outputs here.
    pub fn path(&self) -> &Path {
        &self.stage
    }

    /// The final output directory.
    pub fn out(&self) -> &Path {
        &self.out
    }

    /// Moves every staged file into the output directory (files of the
    /// same names replaced, others kept; summaries last), a new output
    /// directory by renaming the staging directory. If that fails part
    /// way, the files not yet moved stay in the staging directory, which
    /// the error names.
    ///
    /// The files an earlier publish wrote into the directory that this one
    /// did not write are then removed (they are listed in [`MANIFEST`]), so
    /// that the directory holds one run's outputs, not an earlier run's
    /// figures beside this one's summary; files of other origin are kept.
    pub fn publish(mut self) -> Result<()> {
        let mut written = Vec::new();
        list_files(&self.stage, Path::new(""), &mut written)?;
        let listing: String = written
            .iter()
            .map(|p| format!("{}\n", p.display()))
            .collect();
        if !self.out.exists() {
            write_atomic(&self.stage.join(MANIFEST), listing.as_bytes())?;
            if std::fs::rename(&self.stage, &self.out).is_ok() {
                return Ok(());
            }
            // moved file by file below; the list goes last
            let _ = std::fs::remove_file(self.stage.join(MANIFEST));
        }
        let earlier = std::fs::read_to_string(self.out.join(MANIFEST)).unwrap_or_default();
        // a file in the way of a directory, or the reverse, fails before
        // anything moves
        check_tree(&self.stage, &self.out)?;
        move_tree(&self.stage, &self.out).map_err(|e| {
            self.keep = true;
            err!(
                "cannot move the outputs into '{}': {e}; the outputs not moved are in '{}'",
                self.out.display(),
                self.stage.display()
            )
        })?;
        for old in earlier.lines().map(Path::new) {
            if !written.iter().any(|w| w == old) {
                remove_output(&self.out, old);
            }
        }
        write_atomic(&self.out.join(MANIFEST), listing.as_bytes())
    }
}

/// Removes the file `rel` below `out` that an earlier publish wrote, and
/// the directories it leaves empty; nothing outside `out`, and nothing
/// reached through a symbolic link (a directory of the run's replaced by a
/// link to elsewhere).
fn remove_output(out: &Path, rel: &Path) {
    let inside = rel.components().count() > 0
        && rel
            .components()
            .all(|c| matches!(c, std::path::Component::Normal(_)));
    if !inside {
        return;
    }
    let mut dir = out.to_path_buf();
    let parents: Vec<_> = rel
        .parent()
        .map(|p| p.components().collect())
        .unwrap_or_default();
    for c in &parents {
        dir.push(c);
        match std::fs::symlink_metadata(&dir) {
            Ok(m) if m.is_dir() => {}
            _ => return,
        }
    }
    let _ = std::fs::remove_file(out.join(rel));
    // the directories it leaves empty, deepest first (remove_dir fails on
    // a directory that holds anything)
    let mut d = out.join(rel);
    for _ in 0..parents.len() {
        d.pop();
        if std::fs::remove_dir(&d).is_err() {
            break;
        }
    }
}

impl Drop for StagedDir {
    fn drop(&mut self) {
        if !self.keep {
            let _ = std::fs::remove_dir_all(&self.stage);
        }
    }
}

/// The list of the files the last [`StagedDir::publish`] wrote into an
/// output directory (one relative path a line).
pub const MANIFEST: &str = ".bayes-cbf-outputs";

/// Appends the files below `dir` to `out`, as paths relative to it
/// (`prefix` the path of `dir` so far).
fn list_files(dir: &Path, prefix: &Path, out: &mut Vec<PathBuf>) -> Result<()> {
    let entries =
        std::fs::read_dir(dir).with_context(|| format!("cannot read '{}'", dir.display()))?;
    for e in entries {
        let e = e.with_context(|| format!("cannot read '{}'", dir.display()))?;
        let rel = prefix.join(e.file_name());
        if e.path().is_dir() {
            list_files(&e.path(), &rel, out)?;
        } else {
            out.push(rel);
        }
    }
    Ok(())
}

/// Removes the staging directories `dir/{prefix}{pid}-{n}` of processes
/// that no longer run (Linux: no `/proc/{pid}`; elsewhere none is removed).
fn remove_stale(dir: &Path, prefix: &str) {
    if !Path::new("/proc/self").exists() {
        return;
    }
    let Ok(entries) = std::fs::read_dir(dir) else {
        return;
    };
    for e in entries.flatten() {
        let name = e.file_name().to_string_lossy().into_owned();
        let pid = name
            .strip_prefix(prefix)
            .and_then(|rest| rest.split('-').next())
            .and_then(|p| p.parse::<u32>().ok());
        if let Some(pid) = pid {
            let gone = !Path::new("/proc").join(pid.to_string()).exists();
            if gone && e.path().is_dir() {
                let _ = std::fs::remove_dir_all(e.path());
            }
        }
    }
}

/// Checks that every file below `from` can replace its namesake below `to`:
/// no directory stands where a file goes, no file where a directory goes.
fn check_tree(from: &Path, to: &Path) -> Result<()> {
    let entries =
        std::fs::read_dir(from).with_context(|| format!("cannot read '{}'", from.display()))?;
    for e in entries {
        let e = e.with_context(|| format!("cannot read '{}'", from.display()))?;
        let target = to.join(e.file_name());
        let is_dir = e.path().is_dir();
        match std::fs::metadata(&target) {
            Ok(m) if m.is_dir() && !is_dir => {
                return Err(err!(
                    "cannot write output file '{}': a directory of that name exists",
                    target.display()
                ))
            }
            Ok(m) if !m.is_dir() && is_dir => {
                return Err(err!(
                    "cannot create output directory '{}': a file of that name exists",
                    target.display()
                ))
            }
            _ if is_dir => check_tree(&e.path(), &target)?,
            _ => {}
        }
    }
    Ok(())
}

/// Moves every file below `from` to the same place below `to`:
/// subdirectories first, then files, summaries (`*summary.json`) last, so
/// that a directory with its summary holds the rest. A regular file is
/// renamed into place; one the rename cannot place (another file system)
/// and a link, FIFO or device at the target are copied
/// ([`write_via_temp`]).
fn move_tree(from: &Path, to: &Path) -> Result<()> {
    std::fs::create_dir_all(to)
        .with_context(|| format!("cannot create output directory '{}'", to.display()))?;
    let mut entries: Vec<_> = std::fs::read_dir(from)
        .and_then(|d| d.collect::<std::io::Result<Vec<_>>>())
        .with_context(|| format!("cannot read '{}'", from.display()))?;
    entries.sort_by_key(|e| {
        let name = e.file_name().to_string_lossy().into_owned();
        (!e.path().is_dir(), name.ends_with("summary.json"), name)
    });
    for e in entries {
        let (source, target) = (e.path(), to.join(e.file_name()));
        if source.is_dir() {
            move_tree(&source, &target)?;
            continue;
        }
        let plain = match std::fs::symlink_metadata(&target) {
            Ok(m) => m.is_file(),
            Err(_) => true,
        };
        if !(plain && std::fs::rename(&source, &target).is_ok()) {
            copy_to(&source, &target)?;
            let _ = std::fs::remove_file(&source);
        }
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    fn scratch(name: &str) -> PathBuf {
        let dir = std::env::temp_dir().join(format!("bayes-cbf-io-{}-{name}", std::process::id()));
        let _ = std::fs::remove_dir_all(&dir);
        dir
    }

    /// An endless stream is refused at the bound, not read without end; a
    /// file of exactly the bound is read whole; a message names the cause.
    #[test]
    fn input_files_are_read_up_to_a_bound() {
        let e = read_bounded(Path::new("/dev/zero"), 4096).unwrap_err();
        assert!(e.to_string().contains("more than 4096 bytes"), "{e}");
        let dir = scratch("bounded");
        std::fs::create_dir_all(&dir).unwrap();
        let p = dir.join("in.json");
        std::fs::write(&p, [b'x'; 4096]).unwrap();
        assert_eq!(read_bounded(&p, 4096).unwrap().len(), 4096);
        assert!(read_bounded(&p, 4095).is_err());
        std::fs::write(&p, [0xff, 0xfe]).unwrap();
        let e = read_input_text(&p).unwrap_err();
        assert!(e.to_string().contains("not UTF-8"), "{e}");
        let _ = std::fs::remove_dir_all(&dir);
    }

    #[test]
    fn atomic_write_replaces_file() {
        let dir = scratch("replace");
        let p = dir.join("sub").join("out.txt");
        write_atomic(&p, b"one").unwrap();
        write_atomic(&p, b"two").unwrap();
        assert_eq!(std::fs::read_to_string(&p).unwrap(), "two");
        let leftovers = std::fs::read_dir(p.parent().unwrap()).unwrap().count();
        assert_eq!(leftovers, 1);
        std::fs::remove_dir_all(&dir).unwrap();
    }

    #[cfg(unix)]
    #[test]
    fn links_are_written_through_and_fifos_in_place() {
        let dir = scratch("links");
        std::fs::create_dir_all(&dir).unwrap();
        let real = dir.join("real.json");
        std::fs::write(&real, "old").unwrap();
        let link = dir.join("link.json");
        std::os::unix::fs::symlink("real.json", &link).unwrap();
        write_atomic(&link, b"new").unwrap();
        assert!(std::fs::symlink_metadata(&link)
            .unwrap()
            .file_type()
            .is_symlink());
        assert_eq!(std::fs::read_to_string(&real).unwrap(), "new");
        // a dangling link creates its file
        let dangling = dir.join("dangling.json");
        std::os::unix::fs::symlink("made.json", &dangling).unwrap();
        write_atomic(&dangling, b"made").unwrap();
        assert_eq!(
            std::fs::read_to_string(dir.join("made.json")).unwrap(),
            "made"
        );
        // a FIFO is written in place and stays a FIFO
        let fifo = dir.join("fifo");
        let made = std::process::Command::new("mkfifo").arg(&fifo).status();
        if made.is_ok_and(|s| s.success()) {
            // (checked first: a FIFO renamed over would leave the reader waiting)
            assert!(matches!(destination(&fifo), Ok(Destination::Stream(_))));
            let reader = {
                let fifo = fifo.clone();
                std::thread::spawn(move || std::fs::read(fifo).unwrap())
            };
            write_atomic(&fifo, b"through").unwrap();
            assert_eq!(reader.join().unwrap(), b"through");
            assert!(!std::fs::metadata(&fifo).unwrap().is_file());
        }
        let e = write_atomic(&dir, b"x").unwrap_err();
        assert!(e.to_string().contains("is a directory"), "{e}");
        std::fs::remove_dir_all(&dir).unwrap();
    }

    #[test]
    fn a_staged_directory_is_published_whole_or_not_at_all() {
        let dir = scratch("staged");
        let out = dir.join("run");
        let read = |name: &str| std::fs::read_to_string(out.join(name)).unwrap();
        // the entries but the list of the files published (MANIFEST)
        let entries = |p: &Path| {
            let mut v: Vec<String> = std::fs::read_dir(p)
                .unwrap()
                .map(|e| e.unwrap().file_name().to_string_lossy().into_owned())
                .filter(|n| n != MANIFEST)
                .collect();
            v.sort();
            v
        };
        // a new directory: the staging directory renamed
        let st = StagedDir::new(&out).unwrap();
        write_atomic(&st.path().join("summary.json"), b"old").unwrap();
        st.publish().unwrap();
        assert_eq!(entries(&dir), ["run"]);
        // a file of the user's
        std::fs::write(out.join("keep.txt"), "keep").unwrap();
        {
            let st = StagedDir::new(&out).unwrap();
            write_atomic(&st.path().join("summary.json"), b"half").unwrap();
            // dropped without publishing: nothing moves, nothing is left
        }
        assert_eq!(read("summary.json"), "old");
        assert_eq!(entries(&out), ["keep.txt", "summary.json"]);
        // an existing directory: files replaced by name, others kept
        let st = StagedDir::new(&out).unwrap();
        write_atomic(&st.path().join("summary.json"), b"new").unwrap();
        write_atomic(&st.path().join("sub").join("a.csv"), b"a").unwrap();
        st.publish().unwrap();
        assert_eq!(
            (read("summary.json"), read("sub/a.csv"), read("keep.txt")),
            ("new".into(), "a".into(), "keep".into())
        );
        assert_eq!(entries(&out), ["keep.txt", "sub", "summary.json"]);
        // a directory in the way of a file: nothing moves
        std::fs::create_dir_all(out.join("table.csv")).unwrap();
        let st = StagedDir::new(&out).unwrap();
        write_atomic(&st.path().join("a.txt"), b"a").unwrap();
        write_atomic(&st.path().join("table.csv"), b"t").unwrap();
        let e = st.publish().unwrap_err();
        assert!(e.to_string().contains("table.csv': a directory"), "{e}");
        assert_eq!(
            entries(&out),
            ["keep.txt", "sub", "summary.json", "table.csv"]
        );
        // an output path that is a file is refused before anything runs
        let e = StagedDir::new(&out.join("keep.txt")).unwrap_err();
        assert!(e.to_string().contains("not a directory"), "{e}");
        std::fs::remove_dir_all(&dir).unwrap();
    }

    #[cfg(unix)]
    #[test]
    fn a_staged_directory_writes_through_links_and_clears_stale_stages() {
        let dir = scratch("staged-links");
        let out = dir.join("run");
        std::fs::create_dir_all(dir.join("keep")).unwrap();
        std::fs::create_dir_all(&out).unwrap();
        std::fs::write(dir.join("keep").join("summary.json"), "old").unwrap();
        std::os::unix::fs::symlink("../keep/summary.json", out.join("summary.json")).unwrap();
        // an interrupted run's stage (a process that no longer runs)
        let stale = out.join(".staging.tmp-4000000000-0");
        std::fs::create_dir_all(&stale).unwrap();
        // and the stage of an interrupted first run, beside the output
        let beside = dir.join(".run.tmp-4000000000-0");
        std::fs::create_dir_all(&beside).unwrap();
        let st = StagedDir::new(&out).unwrap();
        for s in [&stale, &beside] {
            assert!(!s.exists() || !Path::new("/proc/self").exists(), "{s:?}");
        }
        write_atomic(&st.path().join("summary.json"), b"new").unwrap();
        st.publish().unwrap();
        let link = std::fs::symlink_metadata(out.join("summary.json")).unwrap();
        assert!(link.file_type().is_symlink(), "the link was replaced");
        let kept = std::fs::read_to_string(dir.join("keep").join("summary.json")).unwrap();
        assert_eq!(kept, "new");
        // a link to a missing directory as the output: refused before a run
        std::os::unix::fs::symlink("nowhere", dir.join("dangling")).unwrap();
        let e = StagedDir::new(&dir.join("dangling")).unwrap_err();
        assert!(e.to_string().contains("link to a missing directory"), "{e}");
        std::fs::remove_dir_all(&dir).unwrap();
    }

    /// A directory used again holds the new run's files: an earlier
    /// run's that this one did not write are removed, other files kept.
    #[test]
    fn an_earlier_runs_files_give_way_to_the_next_runs() {
        let dir = scratch("manifest");
        let out = dir.join("out");
        let publish = |files: &[&str]| {
            let st = StagedDir::new(&out).unwrap();
            for f in files {
                let p = st.path().join(f);
                std::fs::create_dir_all(p.parent().unwrap()).unwrap();
                write_atomic(&p, f.as_bytes()).unwrap();
            }
            st.publish().unwrap();
        };
        publish(&["summary.json", "animation.gif", "sub/a.png"]);
        std::fs::write(out.join("notes.txt"), "mine").unwrap();
        publish(&["summary.json", "sweep.csv"]);
        let mut left: Vec<String> = std::fs::read_dir(&out)
            .unwrap()
            .map(|e| e.unwrap().file_name().to_string_lossy().into_owned())
            .filter(|n| !n.starts_with('.'))
            .collect();
        left.sort();
        // sub/a.png removed, and sub with it
        assert_eq!(left, ["notes.txt", "summary.json", "sweep.csv"]);
        // a manifest naming a path outside the directory removes nothing
        std::fs::write(dir.join("outside.txt"), "keep").unwrap();
        std::fs::write(out.join(MANIFEST), "../outside.txt\n").unwrap();
        publish(&["summary.json"]);
        assert!(dir.join("outside.txt").is_file());
        assert!(out.join("notes.txt").is_file());
        // a directory of the run replaced by a link to elsewhere: what the
        // run wrote there is not removed through the link
        #[cfg(unix)]
        {
            publish(&["summary.json", "sub/a.png"]);
            let archive = dir.join("archive");
            std::fs::create_dir_all(&archive).unwrap();
            std::fs::write(archive.join("a.png"), "kept").unwrap();
            std::fs::remove_dir_all(out.join("sub")).unwrap();
            std::os::unix::fs::symlink(&archive, out.join("sub")).unwrap();
            publish(&["summary.json"]);
            assert!(archive.join("a.png").is_file());
        }
        std::fs::remove_dir_all(&dir).unwrap();
    }

    #[test]
    fn own_descriptors_are_written_in_place() {
        for path in ["/dev/stdout", "/dev/fd/1", "/proc/self/fd/1"] {
            assert!(matches!(
                destination(Path::new(path)),
                Ok(Destination::Stdout)
            ));
        }
        for path in ["/dev/stderr", "/dev/fd/2", "/proc/self/fd/2"] {
            assert!(matches!(
                destination(Path::new(path)),
                Ok(Destination::Stderr)
            ));
        }
        assert!(matches!(
            destination(Path::new("/dev/null")),
            Ok(Destination::Stream(_))
        ));
        write_atomic(Path::new("/dev/null"), b"x").unwrap();
    }
}

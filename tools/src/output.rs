//! Files and folders the tools write, whole or not at all: each is written to a temporary file beside its
//! path and renamed over it when complete, so a run that fails or is interrupted leaves what was
//! there before as it was (at most a hidden `.NAME.tmp*` file beside it after a kill). A path that
//! exists and is not a regular file (`/dev/stdout`, a FIFO) is written directly.

use std::fs::File;
use std::io::{BufWriter, Write};
use std::path::{Path, PathBuf};

/// An error naming the file.
fn named(path: &Path, e: impl std::fmt::Display) -> String {
    format!("`{}`: {e}", path.display())
}

/// A special file (a device, a FIFO) is written as it is: it cannot be replaced by a rename.
fn is_special(path: &Path) -> bool {
    std::fs::metadata(path).is_ok_and(|m| !m.is_file() && !m.is_dir())
}

/// Where an output file goes until it is complete.
enum Target {
    Staged(tempfile::NamedTempFile),
    Direct(File),
    Stdout(std::io::Stdout),
}

/// A file being written: [`Write`] into it, then [`OutputFile::commit`]. Dropped without a
/// commit (an error on the way), the temporary file goes and the path keeps what it held.
pub struct OutputFile {
    path: PathBuf,
    out: BufWriter<Target>,
}

impl Write for Target {
    fn write(&mut self, buf: &[u8]) -> std::io::Result<usize> {
        match self {
            Target::Staged(f) => f.write(buf),
            Target::Direct(f) => f.write(buf),
            Target::Stdout(o) => o.write(buf),
        }
    }
    fn flush(&mut self) -> std::io::Result<()> {
        match self {
            Target::Staged(f) => f.flush(),
            Target::Direct(f) => f.flush(),
            Target::Stdout(o) => o.flush(),
        }
    }
}

impl OutputFile {
    /// Starts writing `path` (its directory must exist; `path` must not be a directory).
    pub fn create(path: &Path) -> Result<OutputFile, String> {
        if path.is_dir() {
            return Err(named(path, "is a directory, not a file"));
        }
        let target = if is_special(path) {
            Target::Direct(File::create(path).map_err(|e| named(path, e))?)
        } else {
            let dir = match path.parent() {
                Some(d) if !d.as_os_str().is_empty() => d,
                _ => Path::new("."),
            };
            let name = path.file_name().unwrap_or_default().to_string_lossy();
            let tmp = tempfile::Builder::new()
                .prefix(&format!(".{name}.tmp"))
                .tempfile_in(dir)
                .map_err(|e| named(path, e))?;
            Target::Staged(tmp)
        };
        Ok(OutputFile {
            path: path.to_path_buf(),
            out: BufWriter::new(target),
        })
    }

    /// Writing to standard output instead (`path` only names it in errors): a CLI's output
    /// when no file is given.
    pub fn stdout() -> OutputFile {
        OutputFile {
            path: PathBuf::from("<standard output>"),
            out: BufWriter::new(Target::Stdout(std::io::stdout())),
        }
    }

    /// Everything written: the file takes its place (the rename keeps the permissions a new file
    /// gets, not the temporary file's owner-only ones).
    pub fn commit(self) -> Result<(), String> {
        let path = self.path;
        let target = self.out.into_inner().map_err(|e| named(&path, e.error()))?;
        match target {
            Target::Direct(mut f) => f.flush().map_err(|e| named(&path, e)),
            Target::Stdout(mut o) => o.flush().map_err(|e| named(&path, e)),
            Target::Staged(tmp) => {
                tmp.as_file().sync_all().map_err(|e| named(&path, e))?;
                let mode = 0o666 & !umask();
                use std::os::unix::fs::PermissionsExt;
                std::fs::set_permissions(tmp.path(), std::fs::Permissions::from_mode(mode))
                    .map_err(|e| named(&path, e))?;
                tmp.persist(&path).map_err(|e| named(&path, e.error))?;
                Ok(())
            }
        }
    }
}

impl Write for OutputFile {
    fn write(&mut self, buf: &[u8]) -> std::io::Result<usize> {
        self.out.write(buf)
    }
    fn flush(&mut self) -> std::io::Result<()> {
        self.out.flush()
    }
}

/// Writes `bytes` to `path` whole or not at all ([`OutputFile`]).
pub fn write(path: &Path, bytes: &[u8]) -> Result<(), String> {
    let mut f = OutputFile::create(path)?;
    f.write_all(bytes).map_err(|e| named(path, e))?;
    f.commit()
}

/// A folder written whole or not at all: filled under a hidden temporary name beside `path`, then
/// put in its place by [`OutputDir::commit`]. A folder already at `path` is replaced only when it
/// is empty or `replaceable` says it is an earlier output of the same command; anything else
/// there is refused before any work. Dropped without a commit, the partial folder goes.
pub struct OutputDir {
    path: PathBuf,
    stage: tempfile::TempDir,
}

impl OutputDir {
    pub fn create(
        flag: &str,
        path: &Path,
        replaceable: impl Fn(&Path) -> bool,
    ) -> Result<OutputDir, String> {
        if path.exists() && !path.is_dir() {
            return Err(format!(
                "{flag} `{}`: is a file, not a folder",
                path.display()
            ));
        }
        if path.is_dir() {
            let empty = std::fs::read_dir(path)
                .map_err(|e| named(path, e))?
                .next()
                .is_none();
            if !empty && !replaceable(path) {
                return Err(format!(
                    "{flag} `{}`: the folder holds other files (it is not an earlier output of \
                     this command, which would be replaced); choose a new or empty folder",
                    path.display()
                ));
            }
        }
        let parent = match path.parent() {
            Some(d) if !d.as_os_str().is_empty() => d.to_path_buf(),
            _ => PathBuf::from("."),
        };
        std::fs::create_dir_all(&parent).map_err(|e| named(&parent, e))?;
        let name = path.file_name().unwrap_or_default().to_string_lossy();
        let stage = tempfile::Builder::new()
            .prefix(&format!(".{name}.tmp"))
            .tempdir_in(&parent)
            .map_err(|e| named(path, e))?;
        use std::os::unix::fs::PermissionsExt;
        std::fs::set_permissions(
            stage.path(),
            std::fs::Permissions::from_mode(0o777 & !umask()),
        )
        .map_err(|e| named(path, e))?;
        Ok(OutputDir {
            path: path.to_path_buf(),
            stage,
        })
    }

    /// Where to write until [`OutputDir::commit`].
    pub fn path(&self) -> &Path {
        self.stage.path()
    }

    /// The folder takes its place; what was there before (empty, or an earlier output) goes.
    pub fn commit(self) -> Result<(), String> {
        let path = &self.path;
        // The earlier folder moves into a temporary one, deleted with it at the end.
        let old = match path.exists() {
            true => {
                let parent = self.stage.path().parent().unwrap_or(Path::new("."));
                let old = tempfile::Builder::new()
                    .prefix(".old")
                    .tempdir_in(parent)
                    .map_err(|e| named(path, e))?;
                std::fs::rename(path, old.path().join("x")).map_err(|e| named(path, e))?;
                Some(old)
            }
            false => None,
        };
        let stage = self.stage.keep();
        if let Err(e) = std::fs::rename(&stage, path) {
            // Put the earlier folder back; the new one stays beside it, named.
            if let Some(old) = &old {
                let _ = std::fs::rename(old.path().join("x"), path);
            }
            return Err(named(
                path,
                format!("{e} (the new folder is `{}`)", stage.display()),
            ));
        }
        drop(old);
        Ok(())
    }
}

/// What a command reads: files (and folders, such as `synth --textures`) by canonical path and
/// by (device, inode), so that another spelling of a path or a hard link to an input is that
/// input too. The one check every command that writes makes before any work ([`Inputs::refuse`]):
/// no output may be an input, and no folder it writes or replaces may hold one.
#[derive(Debug, Clone, Default)]
pub struct Inputs {
    pub paths: std::collections::BTreeSet<PathBuf>,
    /// (device, inode) of each input that exists, with its canonical path.
    pub ids: std::collections::HashMap<(u64, u64), PathBuf>,
}

impl Inputs {
    /// The inputs among `files` that exist (one that does not cannot be overwritten).
    pub fn new(files: impl IntoIterator<Item = PathBuf>) -> Inputs {
        use std::os::unix::fs::MetadataExt;
        let mut inputs = Inputs::default();
        for f in files {
            let Ok(real) = f.canonicalize() else { continue };
            if let Ok(m) = std::fs::metadata(&real) {
                inputs.ids.entry((m.dev(), m.ino())).or_insert(real.clone());
            }
            inputs.paths.insert(real);
        }
        inputs
    }

    /// The input `path` is (by any spelling, or a hard link), or with `dir`, the first input
    /// lying in the folder `path` (or being it).
    pub fn hit(&self, path: &Path, dir: bool) -> Option<PathBuf> {
        use std::os::unix::fs::MetadataExt;
        let real = path.canonicalize().ok()?; // not there yet: it cannot be an input
        if dir {
            return self.paths.iter().find(|i| i.starts_with(&real)).cloned();
        }
        if self.paths.contains(&real) {
            return Some(real);
        }
        let m = std::fs::metadata(&real).ok()?;
        self.ids.get(&(m.dev(), m.ino())).cloned()
    }

    /// Refuses `path`, the output of `flag` (with `dir`: a folder the command writes into or
    /// replaces whole), when it is an input or holds one: the error names both.
    pub fn refuse(&self, flag: &str, path: &Path, dir: bool) -> Result<(), String> {
        match (self.hit(path, dir), dir) {
            (None, _) => Ok(()),
            (Some(i), false) => Err(format!(
                "{flag} `{}` is an input of this command (`{}`): it would be overwritten; \
                 choose another path",
                path.display(),
                i.display()
            )),
            (Some(i), true) => Err(format!(
                "{flag} `{}` holds an input of this command, `{}`, which writing the folder \
                 would overwrite or delete; move the input out or choose another folder",
                path.display(),
                i.display()
            )),
        }
    }
}

/// The process's file-creation mask (read by setting it and putting it back).
fn umask() -> u32 {
    // SAFETY: umask only swaps the process's mask; it is put back at once.
    unsafe {
        let m = libc::umask(0o022);
        libc::umask(m);
        m as u32
    }
}

/// The picture format of an output path, by its extension (PNG or JPEG: what the tools encode),
/// checked before a run rather than after it.
pub fn image_format(flag: &str, path: &Path) -> Result<image::ImageFormat, String> {
    let ext = path
        .extension()
        .map(|e| e.to_string_lossy().to_ascii_lowercase());
    match ext.as_deref() {
        Some("png") => Ok(image::ImageFormat::Png),
        Some("jpg" | "jpeg") => Ok(image::ImageFormat::Jpeg),
        Some(e) => Err(format!(
            "{flag} `{}`: cannot write a .{e} picture; name it .png (or .jpg)",
            path.display()
        )),
        None => Err(format!(
            "{flag} `{}`: has no extension to say the picture's format; name it .png (or .jpg)",
            path.display()
        )),
    }
}

/// Encodes `img` in the format of `path`'s extension and writes it whole or not at all.
pub fn save_image(img: &image::RgbImage, path: &Path) -> Result<(), String> {
    let format = image_format("the picture", path)?;
    let mut bytes = std::io::Cursor::new(Vec::new());
    img.write_to(&mut bytes, format)
        .map_err(|e| named(path, e))?;
    write(path, bytes.get_ref())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_failed_write_leaves_the_old_file_and_no_temporary_file() {
        let dir = tempfile::tempdir().unwrap();
        let p = dir.path().join("out.csv");
        std::fs::write(&p, "old\n").unwrap();
        {
            let mut f = OutputFile::create(&p).unwrap();
            writeln!(f, "new, never committed").unwrap();
            f.flush().unwrap();
            assert_eq!(std::fs::read_to_string(&p).unwrap(), "old\n");
        }
        assert_eq!(std::fs::read_to_string(&p).unwrap(), "old\n");
        let names: Vec<_> = std::fs::read_dir(dir.path()).unwrap().collect();
        assert_eq!(names.len(), 1, "{names:?}");
        write(&p, b"new\n").unwrap();
        assert_eq!(std::fs::read_to_string(&p).unwrap(), "new\n");
        use std::os::unix::fs::PermissionsExt;
        let mode = std::fs::metadata(&p).unwrap().permissions().mode() & 0o777;
        assert_eq!(mode, 0o666 & !umask(), "a new file's permissions");
    }

    #[test]
    fn special_files_are_written_directly_and_directories_refused() {
        let dir = tempfile::tempdir().unwrap();
        let e = OutputFile::create(dir.path()).err().unwrap();
        assert!(e.contains("is a directory"), "{e}");
        let mut f = OutputFile::create(Path::new("/dev/null")).unwrap();
        writeln!(f, "x").unwrap();
        f.commit().unwrap();
        // A full device: the error names it, at the latest when the file is committed.
        if Path::new("/dev/full").exists() {
            let r = write(Path::new("/dev/full"), &[0u8; 100_000]);
            assert!(r.unwrap_err().contains("/dev/full"));
        }
    }

    #[test]
    fn a_folder_replaces_only_an_earlier_output_and_appears_whole() {
        let dir = tempfile::tempdir().unwrap();
        let out = dir.path().join("seq");
        let mine = |p: &Path| p.join("made-by-me").exists();
        // A new folder: nothing there until the commit.
        let o = OutputDir::create("--out", &out, mine).unwrap();
        std::fs::write(o.path().join("made-by-me"), "1").unwrap();
        assert!(!out.exists());
        o.commit().unwrap();
        assert_eq!(
            std::fs::read_to_string(out.join("made-by-me")).unwrap(),
            "1"
        );
        use std::os::unix::fs::PermissionsExt;
        let mode = std::fs::metadata(&out).unwrap().permissions().mode() & 0o777;
        assert_eq!(mode, 0o777 & !umask());
        // An earlier output is replaced whole (its other files go too); one dropped half-way
        // leaves it as it was.
        std::fs::write(out.join("old-frame"), "x").unwrap();
        let o = OutputDir::create("--out", &out, mine).unwrap();
        std::fs::write(o.path().join("half"), "x").unwrap();
        drop(o);
        assert!(out.join("old-frame").exists());
        let o = OutputDir::create("--out", &out, mine).unwrap();
        std::fs::write(o.path().join("made-by-me"), "2").unwrap();
        o.commit().unwrap();
        assert_eq!(
            std::fs::read_to_string(out.join("made-by-me")).unwrap(),
            "2"
        );
        assert!(!out.join("old-frame").exists());
        // Only the folder is left beside it: no staging or old copies.
        assert_eq!(std::fs::read_dir(dir.path()).unwrap().count(), 1);
        // Someone else's folder, or a file, is refused before any work and kept.
        let theirs = dir.path().join("theirs");
        std::fs::create_dir(&theirs).unwrap();
        std::fs::write(theirs.join("notes.txt"), "keep").unwrap();
        let e = OutputDir::create("--out", &theirs, mine).err().unwrap();
        assert!(e.contains("holds other files"), "{e}");
        assert_eq!(
            std::fs::read_to_string(theirs.join("notes.txt")).unwrap(),
            "keep"
        );
        let e = OutputDir::create("--out", &theirs.join("notes.txt"), mine)
            .err()
            .unwrap();
        assert!(e.contains("is a file, not a folder"), "{e}");
        // An empty folder is taken.
        let empty = dir.path().join("empty");
        std::fs::create_dir(&empty).unwrap();
        let o = OutputDir::create("--out", &empty, mine).unwrap();
        o.commit().unwrap();
        assert!(empty.is_dir());
    }

    #[test]
    fn picture_formats_are_known_from_the_extension_before_a_run() {
        assert!(image_format("--plot", Path::new("a/b.PNG")).is_ok());
        assert!(image_format("--plot", Path::new("b.jpeg")).is_ok());
        let e = image_format("--plot", Path::new("p.txt")).unwrap_err();
        assert_eq!(
            e,
            "--plot `p.txt`: cannot write a .txt picture; name it .png (or .jpg)"
        );
        assert!(image_format("--plot", Path::new("plot"))
            .unwrap_err()
            .contains("no extension"));
    }
}

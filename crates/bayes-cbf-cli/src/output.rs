//! JSON results on stdout, or in a file written completely or not at all
//! (`--out -` is stdout, as usual on the command line).

use anyhow::{bail, Context, Result};
use bayes_cbf_scenario::io::write_atomic;
use serde::Serialize;
use std::io::Write;
use std::path::{Path, PathBuf};

/// Writes `value` as JSON (one line, or indented with `pretty`) and a final
/// newline to `out`, or to stdout when `out` is `None`.
pub fn emit<T: Serialize + ?Sized>(value: &T, out: &Option<PathBuf>, pretty: bool) -> Result<()> {
    let mut json = if pretty {
        serde_json::to_string_pretty(value)
    } else {
        serde_json::to_string(value)
    }
    .context("cannot serialise the output")?;
    json.push('\n');
    match out {
        Some(p) => write_out(p, json.as_bytes()),
        None => print_stdout(&json),
    }
}

/// Writes `bytes` to the file `path` completely or not at all, or to
/// stdout when `path` is `-`.
pub fn write_out(path: &Path, bytes: &[u8]) -> Result<()> {
    if path == Path::new("-") {
        return print_stdout(&String::from_utf8_lossy(bytes));
    }
    Ok(write_atomic(path, bytes)?)
}

/// Refuses an output path that is one of the command's input files (given
/// as `(option, path)`): the output would replace the input it was made
/// from. An output that does not exist yet cannot be one.
pub fn refuse_input_as_output(out: &Path, inputs: &[(&str, &Path)]) -> Result<()> {
    let Ok(o) = out.canonicalize() else {
        return Ok(());
    };
    for (option, input) in inputs {
        if input.canonicalize().is_ok_and(|i| i == o) {
            bail!(
                "--out '{}' is the {option} file '{}': the output would replace it; write it \
                 elsewhere",
                out.display(),
                input.display()
            );
        }
    }
    Ok(())
}

/// Writes `text` to stdout; a full disk or a closed pipe is an error, not
/// a panic.
pub fn print_stdout(text: &str) -> Result<()> {
    let mut o = std::io::stdout().lock();
    o.write_all(text.as_bytes())
        .and_then(|()| o.flush())
        .context("cannot write to stdout")
}

//! How a Python tool of the project refuses bad input: one line, no traceback.

/// Assert a clean refusal: a non-zero exit, no Python traceback, and the last line of stderr
/// naming `needle` (the file or argument at fault). `what` labels the failure messages. Returns
/// stderr for further checks.
pub fn assert_refused(out: &std::process::Output, what: &str, needle: &str) -> String {
    let err = String::from_utf8_lossy(&out.stderr).into_owned();
    assert!(!out.status.success(), "{what}: accepted\n{err}");
    assert!(!err.contains("Traceback"), "{what}: {err}");
    let last = err.lines().last().unwrap_or("");
    assert!(last.contains(needle), "{what}: `{needle}` not named: {err}");
    err
}

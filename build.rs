//! The git commit `visnav --version` prints (`VISNAV_GIT_COMMIT`): the short hash, `-dirty` when
//! the working tree has changes, `unknown` when the build is not from a git checkout (a source
//! tarball, a vendored copy) or git is not installed. A build never fails for want of git.

use std::process::Command;

/// What `--version` says when git cannot tell.
const UNKNOWN: &str = "unknown";

/// `git ARGS` in the package's folder: its trimmed stdout when it succeeds.
fn git(args: &[&str]) -> Option<String> {
    let dir = std::env::var_os("CARGO_MANIFEST_DIR")?;
    // `--no-optional-locks`: `git status` would otherwise refresh .git/index, which this script
    // watches, and so make every build re-run it.
    let out = Command::new("git")
        .arg("--no-optional-locks")
        .args(args)
        .current_dir(dir)
        .output()
        .ok()?;
    if !out.status.success() {
        return None;
    }
    String::from_utf8(out.stdout)
        .ok()
        .map(|s| s.trim().to_string())
}

fn main() {
    // Re-run when the commit changes (HEAD moves to another branch, the branch to another
    // commit, a commit or `git add` rewrites the index) and when the sources change, which can
    // make the tree dirty or clean again. Without a git checkout these paths do not exist, and
    // cargo then re-runs the script on every build, which costs only the failing git call.
    for watched in ["src", "crates", "Cargo.toml", "Cargo.lock", "build.rs"] {
        println!("cargo:rerun-if-changed={watched}");
    }
    for path in ["HEAD", "index", "packed-refs"] {
        if let Some(p) = git(&["rev-parse", "--git-path", path]) {
            println!("cargo:rerun-if-changed={p}");
        }
    }
    if let Some(head_ref) = git(&["symbolic-ref", "-q", "HEAD"])
        && let Some(p) = git(&["rev-parse", "--git-path", &head_ref])
    {
        println!("cargo:rerun-if-changed={p}");
    }
    let commit = match git(&["rev-parse", "--short", "HEAD"]) {
        Some(hash) if !hash.is_empty() => {
            // Untracked files count too: a new source file not yet added changes the build.
            let dirty = git(&["status", "--porcelain"]).is_some_and(|s| !s.is_empty());
            if dirty { format!("{hash}-dirty") } else { hash }
        }
        _ => UNKNOWN.to_string(),
    };
    println!("cargo:rustc-env=VISNAV_GIT_COMMIT={commit}");
}

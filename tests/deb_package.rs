//! `scripts/build_deb.sh` end to end: a .deb built from the test's binary and read back with
//! dpkg-deb: its files (`-c`), its control fields, conffiles and maintainer scripts (`-I`, `-e`),
//! and its contents unpacked into a temporary root (`-x`), where the binary runs and the unit and
//! the configuration are scripts/install.sh's. The postinst runs against stand-in commands (no
//! user is created here). Skips with a printed reason where dpkg-deb is absent. The package is
//! built uncompressed: the test binary is large and xz would take most of a minute.

use std::os::unix::fs::PermissionsExt;
use std::path::{Path, PathBuf};
use std::process::{Command, Output};

fn repo() -> PathBuf {
    PathBuf::from(env!("CARGO_MANIFEST_DIR"))
}

use crate::common::{assert_ok, text};

/// Runs `program args`, asserts success, returns its stdout.
fn run(program: impl AsRef<std::ffi::OsStr>, args: &[&std::ffi::OsStr]) -> String {
    let program = program.as_ref();
    let out = Command::new(program).args(args).output().unwrap();
    assert_ok(&out, &program.to_string_lossy());
    text(&out.stdout)
}

/// `Key: value` fields of a control file (continuation lines left out).
fn field<'a>(control: &'a str, key: &str) -> Option<&'a str> {
    control
        .lines()
        .find_map(|l| l.strip_prefix(key)?.strip_prefix(':').map(str::trim))
}

/// The lines of a file that are not comments: what two installs must agree on.
fn body(path: &Path) -> Vec<String> {
    std::fs::read_to_string(path)
        .unwrap()
        .lines()
        .filter(|l| !l.trim_start().starts_with('#'))
        .map(str::to_string)
        .collect()
}

/// A shell script's command lines: no comments, no here-document text (the next steps it
/// prints name commands it does not run).
fn code_lines(script: &str) -> Vec<&str> {
    let mut out = Vec::new();
    let mut until: Option<String> = None;
    for l in script.lines() {
        if let Some(end) = &until {
            if l.trim() == end {
                until = None;
            }
            continue;
        }
        if l.trim_start().starts_with('#') {
            continue;
        }
        if let Some((_, tag)) = l.split_once("<<") {
            let tag = tag.trim().trim_matches(['\'', '"', '-']);
            if !tag.is_empty() {
                until = Some(tag.to_string());
            }
        }
        out.push(l);
    }
    out
}

/// Stand-ins for the commands the maintainer scripts call to change the system: each writes its
/// name and arguments to `log` and succeeds; `getent` knows the groups and not the user.
fn stub_commands(dir: &Path, log: &Path, names: &[&str]) {
    std::fs::create_dir_all(dir).unwrap();
    for name in names {
        let body = if *name == "getent" {
            format!(
                "#!/bin/sh\necho \"getent $*\" >> '{}'\n[ \"$1\" = group ]\n",
                log.display()
            )
        } else {
            format!("#!/bin/sh\necho \"{name} $*\" >> '{}'\n", log.display())
        };
        let p = dir.join(name);
        std::fs::write(&p, body).unwrap();
        std::fs::set_permissions(&p, std::fs::Permissions::from_mode(0o755)).unwrap();
    }
}

/// The postinst `configure` on a first install with the stand-ins in `stubs` first in PATH and
/// `path_rest` after them; returns its output and the commands it called.
fn postinst(script: &Path, dir: &Path, stubs: &[&str], path_rest: &str) -> (Output, String) {
    let bin = dir.join("bin");
    let log = dir.join("calls.log");
    let root = dir.join("root");
    std::fs::create_dir_all(&root).unwrap();
    stub_commands(&bin, &log, stubs);
    let out = Command::new("sh")
        .arg(script)
        .arg("configure")
        .env("PATH", format!("{}:{path_rest}", bin.display()))
        .env("DPKG_ROOT", &root)
        .output()
        .unwrap();
    assert_ok(&out, "postinst configure");
    assert!(
        root.join("var/log/visnav").is_dir(),
        "postinst made no $DPKG_ROOT/var/log/visnav"
    );
    let calls = std::fs::read_to_string(&log).unwrap_or_default();
    (out, calls)
}

#[test]
fn deb_holds_the_installers_files_and_creates_the_user() {
    if Command::new("dpkg-deb").arg("--version").output().is_err() {
        println!("skipped: dpkg-deb is not installed here (the dpkg package: Debian or Ubuntu)");
        return;
    }
    let bin = env!("CARGO_BIN_EXE_visnav");
    let arch = run("dpkg", &["--print-architecture".as_ref()])
        .trim()
        .to_string();
    let dir = tempfile::tempdir().unwrap();
    let out = dir.path().join("out");

    // Build.
    let built = Command::new(repo().join("scripts/build_deb.sh"))
        .args(["--compression", "none", bin])
        .arg(&out)
        .output()
        .unwrap();
    assert_ok(&built, "scripts/build_deb.sh");
    let deb = PathBuf::from(text(&built.stdout).trim());
    let name = format!("visnav_{}_{arch}.deb", env!("CARGO_PKG_VERSION"));
    assert_eq!(deb, out.join(&name));
    assert!(deb.is_file(), "{} not written", deb.display());
    let d = deb.as_os_str();

    // The files (-c): binary, unit, configuration, all root's; the unit where packages put theirs
    // and the flight records' folder left to postinst (it belongs to the visnav user).
    let list = run("dpkg-deb", &["-c".as_ref(), d]);
    for f in [
        "./usr/bin/visnav",
        "./usr/lib/systemd/system/visnav.service",
        "./etc/visnav/visnav.toml",
    ] {
        assert!(
            list.lines().any(|l| l.ends_with(&format!(" {f}"))),
            "{f} not in the package:\n{list}"
        );
    }
    assert!(
        list.lines().all(|l| l.contains(" root/root ")),
        "files not owned by root:\n{list}"
    );
    assert!(
        !list.contains("./etc/systemd/") && !list.contains("./var/"),
        "{list}"
    );

    // The control fields (-I).
    let control = run("dpkg-deb", &["-I".as_ref(), d, "control".as_ref()]);
    assert_eq!(field(&control, "Package"), Some("visnav"), "{control}");
    assert_eq!(
        field(&control, "Version"),
        Some(env!("CARGO_PKG_VERSION")),
        "{control}"
    );
    assert_eq!(
        field(&control, "Architecture"),
        Some(arch.as_str()),
        "{control}"
    );
    let depends = field(&control, "Depends").unwrap_or_default();
    assert!(
        depends.contains("libc6 (>= 2.") && depends.contains("adduser | passwd"),
        "Depends: {depends}"
    );
    assert!(field(&control, "Maintainer").is_some_and(|m| m.contains('@')));
    let conffiles = run("dpkg-deb", &["-I".as_ref(), d, "conffiles".as_ref()]);
    assert!(
        conffiles.lines().any(|l| l == "/etc/visnav/visnav.toml"),
        "conffiles:\n{conffiles}"
    );

    // The maintainer scripts: executable, valid sh, enabling and starting nothing.
    let control_dir = dir.path().join("DEBIAN");
    run("dpkg-deb", &["-e".as_ref(), d, control_dir.as_os_str()]);
    for s in ["postinst", "prerm", "postrm"] {
        let p = control_dir.join(s);
        let mode = std::fs::metadata(&p).unwrap().permissions().mode();
        assert_eq!(mode & 0o755, 0o755, "{s}: mode {mode:o}");
        run("sh", &["-n".as_ref(), p.as_os_str()]);
        let t = std::fs::read_to_string(&p).unwrap();
        let code = code_lines(&t);
        for no in ["systemctl enable", "systemctl start"] {
            assert!(!code.iter().any(|l| l.contains(no)), "{s} runs '{no}'");
        }
    }

    // postinst with adduser: the system user, its groups, the records' folder; no enable.
    let post = control_dir.join("postinst");
    let stubs = [
        "getent",
        "adduser",
        "useradd",
        "usermod",
        "chown",
        "systemctl",
    ];
    let (o, calls) = postinst(&post, &dir.path().join("p1"), &stubs, "/usr/bin:/bin");
    assert!(
        calls.contains("adduser --system --group --no-create-home")
            && calls.contains("adduser --quiet visnav dialout")
            && calls.contains("adduser --quiet visnav video")
            && calls.contains("chown visnav:visnav"),
        "postinst calls:\n{calls}"
    );
    assert!(
        !calls.contains("systemctl enable") && !calls.contains("systemctl start"),
        "{calls}"
    );
    assert!(text(&o.stdout).contains("not enabled and not started"));
    // Without adduser (a minimal system): useradd and usermod from passwd.
    let (_, calls) = postinst(
        &post,
        &dir.path().join("p2"),
        &["getent", "useradd", "usermod", "chown", "systemctl"],
        "/usr/bin:/bin",
    );
    if calls.contains("adduser") {
        println!("adduser is in /usr/bin or /bin here: the useradd branch was not exercised");
    } else {
        assert!(
            calls.contains("useradd --system --user-group --no-create-home")
                && calls.contains("usermod -a -G dialout visnav"),
            "postinst calls without adduser:\n{calls}"
        );
    }

    // Unpacked (-x) into a temporary root: the binary runs; the unit and the configuration are
    // what scripts/install.sh installs with the same prefix (one source for each).
    let root = dir.path().join("root");
    run("dpkg-deb", &["-x".as_ref(), d, root.as_os_str()]);
    let v = run(root.join("usr/bin/visnav"), &["--version".as_ref()]);
    assert!(v.starts_with("visnav "), "{v}");
    let unit = root.join("usr/lib/systemd/system/visnav.service");
    let unit_text = std::fs::read_to_string(&unit).unwrap();
    assert!(
        unit_text.contains("ExecStart=/usr/bin/visnav run --config /etc/visnav/visnav.toml")
            && unit_text.contains("User=visnav")
            && !unit_text.contains("install.sh"),
        "{unit_text}"
    );
    let conf = root.join("etc/visnav/visnav.toml");
    let conf_text = std::fs::read_to_string(&conf).unwrap();
    assert!(
        conf_text.starts_with("# Installed by the visnav ")
            && !conf_text.contains(&*repo().to_string_lossy()),
        "{conf_text}"
    );
    let by_script = dir.path().join("by-install-sh");
    std::fs::create_dir_all(&by_script).unwrap();
    run(
        repo().join("scripts/install.sh"),
        &[
            "--root".as_ref(),
            by_script.as_os_str(),
            "--prefix".as_ref(),
            "/usr".as_ref(),
            "--binary".as_ref(),
            bin.as_ref(),
            "--no-enable".as_ref(),
        ],
    );
    assert_eq!(
        body(&unit),
        body(&by_script.join("etc/systemd/system/visnav.service"))
    );
    assert_eq!(body(&conf), body(&by_script.join("etc/visnav/visnav.toml")));
}

//! Nothing half-written: a writer killed (`SIGKILL`) in the middle of writing an output leaves
//! the old output or none, never a partial one; a full disk is a one-line error that leaves the
//! old output as it was.
//!
//! The kill lands mid-write by construction, not by timing: before the writer gets to its
//! output, the test puts a FIFO (with a 4 KB pipe) where the writer's temporary file goes
//! (`.<name>.tmp-<pid>`, [`prl_runtime::temporary_path`]); the writer opens it, fills the pipe
//! and blocks with the rest of its output unwritten; the test reads a few bytes of it and kills
//! the writer there. A writer that wrote its output in place would never open the FIFO and the
//! test would fail.

mod common;

use std::io::Read;
use std::os::unix::fs::{FileTypeExt, OpenOptionsExt};
use std::os::unix::process::CommandExt;
use std::path::{Path, PathBuf};
use std::process::{Command, Stdio};
use std::time::{Duration, Instant};

fn prl_cmd(args: &[&str]) -> Command {
    let mut c = Command::new(env!("CARGO_BIN_EXE_prl"));
    c.args(args).current_dir(env!("CARGO_MANIFEST_DIR")).stdout(Stdio::null()).stderr(Stdio::piped());
    c
}

/// Run `cmd`, which writes `output`, and kill it with `SIGKILL` once it has written part of
/// `output`'s temporary file; returns the bytes it had written (at least one).
fn kill_mid_write(mut cmd: Command, output: &Path) -> Vec<u8> {
    let mut child = cmd.spawn().unwrap();
    // The writer's temporary: as [`prl_runtime::temporary_path`] names it, with the writer's pid.
    let temporary =
        |pid: u32| output.with_file_name(format!(".{}.tmp-{pid}", output.file_name().unwrap().to_string_lossy()));
    assert_eq!(prl_runtime::temporary_path(output), temporary(std::process::id()));
    let fifo = temporary(child.id());
    let c = std::ffi::CString::new(fifo.as_os_str().as_encoded_bytes()).unwrap();
    // SAFETY: `c` is a NUL-terminated path that outlives the call.
    assert_eq!(unsafe { libc::mkfifo(c.as_ptr(), 0o600) }, 0, "mkfifo {}", fifo.display());
    // Non-blocking: opening does not wait for the writer, reading returns what is there.
    let mut reader = std::fs::OpenOptions::new().read(true).custom_flags(libc::O_NONBLOCK).open(&fifo).unwrap();
    // SAFETY: F_SETPIPE_SZ on a FIFO this process holds open; no memory is passed.
    unsafe { libc::fcntl(std::os::fd::AsRawFd::as_raw_fd(&reader), libc::F_SETPIPE_SZ, 4096) };
    let start = Instant::now();
    let mut got = vec![0u8; 64];
    loop {
        match reader.read(&mut got) {
            Ok(n) if n > 0 => {
                got.truncate(n);
                break;
            }
            _ => {}
        }
        if let Some(status) = child.try_wait().unwrap() {
            let mut err = String::new();
            child.stderr.take().unwrap().read_to_string(&mut err).unwrap();
            panic!("the writer ended ({status}) without writing through {}: {err}", fifo.display());
        }
        assert!(start.elapsed() < Duration::from_secs(300), "the writer never reached its output");
        std::thread::sleep(Duration::from_millis(2));
    }
    // The writer has filled the 4 KB pipe and waits for it to drain: it is mid-write.
    std::thread::sleep(Duration::from_millis(50));
    assert!(child.try_wait().unwrap().is_none(), "the writer finished though its output was not all read");
    child.kill().unwrap();
    let status = child.wait().unwrap();
    assert_eq!(std::os::unix::process::ExitStatusExt::signal(&status), Some(libc::SIGKILL));
    assert!(std::fs::symlink_metadata(&fifo).unwrap().file_type().is_fifo());
    std::fs::remove_file(&fifo).unwrap();
    got
}

/// Every file in `dir` with its bytes, by name.
fn read_set(dir: &Path) -> Vec<(String, Vec<u8>)> {
    let mut v: Vec<_> = std::fs::read_dir(dir)
        .unwrap()
        .map(|e| e.unwrap())
        .map(|e| (e.file_name().to_string_lossy().into_owned(), std::fs::read(e.path()).unwrap()))
        .collect();
    v.sort();
    v
}

/// The files of `dir` under their final names: what a reader sees (a killed writer's
/// temporaries, `.<name>.tmp-<pid>`, are left behind; nothing reads them).
fn committed(dir: &Path) -> Vec<(String, Vec<u8>)> {
    read_set(dir).into_iter().filter(|(n, _)| !(n.starts_with('.') && n.contains(".tmp-"))).collect()
}

/// The file of a plan or model directory's manifest names for `graph` (`search`, ...).
fn graph_file(dir: &Path, manifest: &str, graph: &str) -> String {
    let m: serde_json::Value = serde_json::from_slice(&std::fs::read(dir.join(manifest)).unwrap()).unwrap();
    m[graph]["file"].as_str().unwrap().to_string()
}

#[test]
fn killed_writers_leave_the_old_output_or_none() {
    let d = tempfile::tempdir().unwrap();
    let p = |n: &str| d.path().join(n);
    let s = |p: &PathBuf| p.to_str().unwrap().to_string();
    let seq = s(&common::sequence("building4"));
    common::ok(&common::prl(&["import", "nanotrack", "--out", &s(&p("model"))]));
    common::ok(&common::prl(&["compile", "--model", &s(&p("model")), "--out", &s(&p("plan"))]));

    // Results of `prl track` (8 KB for building4) over an old file.
    let results = p("results.txt");
    std::fs::write(&results, "old\n").unwrap();
    let partial = kill_mid_write(
        prl_cmd(&["track", "--plan", &s(&p("plan")), "--sequence", &seq, "--results", &s(&results)]),
        &results,
    );
    assert!(!partial.is_empty() && partial != b"old\n");
    assert_eq!(std::fs::read(&results).unwrap(), b"old\n", "the old results survive");
    // The same into a fresh name: none.
    let fresh = p("fresh.txt");
    kill_mid_write(prl_cmd(&["track", "--plan", &s(&p("plan")), "--sequence", &seq, "--results", &s(&fresh)]), &fresh);
    assert!(!fresh.exists());

    // A plan recompiled over an old one, killed while writing its search graph, then its
    // manifest: the old plan, byte for byte, loads.
    let old_plan = read_set(&p("plan"));
    for graph in ["template", "search"] {
        let file = graph_file(&p("plan"), "plan.json", graph);
        let cmd = prl_cmd(&["compile", "--model", &s(&p("model")), "--out", &s(&p("plan"))]);
        kill_mid_write(cmd, &p("plan").join(&file));
        assert_eq!(committed(&p("plan")), old_plan, "killed while writing {file}");
    }
    prl_runtime::Plan::load(p("plan")).expect("the old plan loads");
    // Into a fresh folder: no manifest, so no plan.
    std::fs::create_dir(p("plan2")).unwrap();
    let search = p("plan2").join(graph_file(&p("plan"), "plan.json", "search"));
    kill_mid_write(prl_cmd(&["compile", "--model", &s(&p("model")), "--out", &s(&p("plan2"))]), &search);
    assert!(!p("plan2/plan.json").exists());
    let err = prl_runtime::Plan::load(p("plan2")).err().expect("no plan").to_string();
    assert!(err.contains("plan.json") && err.contains("No such file"), "{err}");

    // A model directory imported over an old one.
    let old_model = read_set(&p("model"));
    let file = graph_file(&p("model"), "manifest.json", "search");
    kill_mid_write(prl_cmd(&["import", "nanotrack", "--out", &s(&p("model"))]), &p("model").join(file));
    assert_eq!(committed(&p("model")), old_model);
}

/// `prl` with its file-size limit at `limit` bytes and `SIGXFSZ` ignored: a write past it fails
/// with `EFBIG`, as a write to a full disk fails with `ENOSPC`.
fn prl_with_file_limit(args: &[&str], limit: u64) -> std::process::Output {
    let mut c = prl_cmd(args);
    // SAFETY: between fork and exec only async-signal-safe calls (setrlimit, signal) are made,
    // on values owned by this closure.
    unsafe {
        c.pre_exec(move || {
            let lim = libc::rlimit { rlim_cur: limit, rlim_max: limit };
            if libc::setrlimit(libc::RLIMIT_FSIZE, &lim) != 0
                || libc::signal(libc::SIGXFSZ, libc::SIG_IGN) == libc::SIG_ERR
            {
                return Err(std::io::Error::last_os_error());
            }
            Ok(())
        })
    };
    c.output().unwrap()
}

fn one_line_error(o: &std::process::Output, names: &str, says: &str) {
    let err = String::from_utf8_lossy(&o.stderr);
    assert_eq!(o.status.code(), Some(1), "{err}");
    assert_eq!(err.trim().lines().count(), 1, "{err}");
    assert!(err.contains(names) && err.contains(says), "{err}");
}

#[test]
fn a_full_disk_is_a_one_line_error_and_the_old_output_stays() {
    let d = tempfile::tempdir().unwrap();
    let s = |p: &Path| p.to_str().unwrap().to_string();
    let (model, plan) = (d.path().join("model"), d.path().join("plan"));
    common::ok(&common::prl(&["import", "nanotrack", "--out", &s(&model)]));
    common::ok(&common::prl(&["compile", "--model", &s(&model), "--out", &s(&plan)]));
    let seq = s(&common::sequence("building4"));
    let results = d.path().join("results.txt");
    std::fs::write(&results, "old\n").unwrap();
    let track = ["track", "--plan", &s(&plan), "--sequence", &seq, "--results", &s(&results)];
    let o = prl_with_file_limit(&track, 2048);
    one_line_error(&o, "results.txt: cannot write", "File too large");
    assert_eq!(std::fs::read(&results).unwrap(), b"old\n");
    let old_plan = read_set(&plan);
    let o = prl_with_file_limit(&["compile", "--model", &s(&model), "--out", &s(&plan)], 64 << 10);
    one_line_error(&o, &s(&plan), "File too large");
    assert_eq!(read_set(&plan), old_plan, "the old plan stays whole, and no temporary is left");

    // A real full disk: a 1 MB tmpfs, filled. Mounting needs root (CI runs as root).
    let mnt = d.path().join("small");
    std::fs::create_dir(&mnt).unwrap();
    let mounted = Command::new("mount").args(["-t", "tmpfs", "-o", "size=1m", "tmpfs"]).arg(&mnt).output();
    if !mounted.as_ref().is_ok_and(|o| o.status.success()) {
        eprintln!(
            "SKIPPED (loudly): the ENOSPC half of this test needs root to mount a small tmpfs ({}); \
             the file-size-limit half above ran",
            mounted.map(|o| String::from_utf8_lossy(&o.stderr).trim().to_string()).unwrap_or_else(|e| e.to_string())
        );
        return;
    }
    struct Unmount(PathBuf);
    impl Drop for Unmount {
        fn drop(&mut self) {
            let _ = Command::new("umount").arg(&self.0).status();
        }
    }
    let _unmount = Unmount(mnt.clone());
    let results = mnt.join("results.txt");
    std::fs::write(&results, "old\n").unwrap();
    // Fill what is left (writes stop at ENOSPC).
    let mut fill = std::fs::File::create(mnt.join("fill")).unwrap();
    let chunk = vec![0u8; 4096];
    while std::io::Write::write_all(&mut fill, &chunk).is_ok() {}
    drop(fill);
    let track = ["track", "--plan", &s(&plan), "--sequence", &seq, "--results", &s(&results)];
    let o = prl_cmd(&track).output().unwrap();
    one_line_error(&o, "results.txt: cannot write", "No space left on device");
    assert_eq!(std::fs::read(&results).unwrap(), b"old\n");
    assert_eq!(std::fs::read_dir(&mnt).unwrap().count(), 2, "no temporary left");
}

//! `prl track --video`: a video FFmpeg encodes losslessly from a sequence's decoded frames gives
//! exactly the boxes the frame folder gives; live pacing drops frames when the tracker is slower
//! than the source and says how many; a UDP stream tracks live until Ctrl-C, which writes the
//! results; an RTSP camera (GStreamer's RTSP server, `scripts/rtsp-server.py`) tracks live until
//! its stream ends; a missing file or camera device is a one-line error. Needs the `ffmpeg` and `ffprobe`
//! programs, and for RTSP the server's packages (`.ci/run` installs them all); without them
//! these tests say so and pass.

mod common;

use std::io::Write;
use std::path::Path;
use std::process::{Command, Stdio};

fn have_ffmpeg() -> bool {
    let ok = ["ffmpeg", "ffprobe"]
        .iter()
        .all(|t| Command::new(t).arg("-version").stdout(Stdio::null()).stderr(Stdio::null()).status().is_ok());
    if !ok {
        eprintln!(
            "NOTE: ffmpeg/ffprobe not found: the video input tests are NOT run here (sudo apt-get install ffmpeg)"
        );
    }
    ok
}

/// FFV1 (lossless, `bgr0`) of `frames` BGR frames of `w`x`h`, piped raw into ffmpeg.
fn encode(out: &Path, w: usize, h: usize, frames: impl Iterator<Item = Vec<u8>>) {
    let mut ff = Command::new("ffmpeg")
        .args(["-hide_banner", "-loglevel", "error", "-f", "rawvideo", "-pix_fmt", "bgr24", "-s"])
        .arg(format!("{w}x{h}"))
        .args(["-r", "10", "-i", "-", "-c:v", "ffv1", "-pix_fmt", "bgr0", "-y"])
        .arg(out)
        .stdin(Stdio::piped())
        .spawn()
        .unwrap();
    let mut stdin = ff.stdin.take().unwrap();
    for f in frames {
        stdin.write_all(&f).unwrap();
    }
    drop(stdin);
    assert!(ff.wait().unwrap().success());
}

/// `n` BGR frames of `w`x`h` vertical stripes moving 2 pixels a frame.
fn stripes(w: usize, h: usize, n: usize) -> impl Iterator<Item = Vec<u8>> {
    (0..n).map(move |i| (0..w * h * 3).map(|k| ((k / 3 % w + 2 * i) % 256) as u8).collect())
}

#[test]
fn a_lossless_video_tracks_exactly_as_its_frames() {
    if !have_ffmpeg() {
        return;
    }
    let tmp = tempfile::tempdir().unwrap();
    let plan = common::nanotrack_plan(tmp.path());
    let seq = prl_track::Sequence::open(&common::sequence("building4")).unwrap();
    let n = 25;
    let first = prl_track::load_frame(&seq.frames[0]).unwrap();
    let (w, h) = (first.width(), first.height());
    let video = tmp.path().join("building4.mkv");
    encode(&video, w, h, seq.frames[..n].iter().map(|p| prl_track::load_frame(p).unwrap().bgr().to_vec()));
    let s = |p: &Path| p.to_str().unwrap().to_string();
    let init = seq.groundtruth().unwrap()[0];
    let init = format!("{},{},{},{}", init[0] - 1.0, init[1] - 1.0, init[2], init[3]);
    let (from_video, from_frames) = (tmp.path().join("video.txt"), tmp.path().join("frames.txt"));
    let (plan_s, video_s) = (s(&plan), s(&video));
    // `prl track` on the video with `extra` options.
    let on_video = |extra: &[&str]| {
        let base = ["track", "--plan", plan_s.as_str(), "--video", video_s.as_str(), "--init", init.as_str()];
        common::prl(&[&base[..], extra].concat())
    };
    let out = common::ok(&on_video(&["--results", &s(&from_video)]));
    assert!(out.contains("frames: 25 tracked, 0 dropped"), "{out}");
    let seq_dir = s(&common::sequence("building4"));
    let n_s = n.to_string();
    let frames_args = ["--sequence", &seq_dir, "--init", &init, "--max-frames", &n_s, "--results", &s(&from_frames)];
    common::ok(&common::prl(&[&["track", "--plan", &plan_s][..], &frames_args].concat()));
    let (a, b) = (std::fs::read_to_string(&from_video).unwrap(), std::fs::read_to_string(&from_frames).unwrap());
    assert_eq!(a.lines().count(), n);
    assert_eq!(a, b, "the video's boxes differ from the frames'");
    // --jsonl: one object a frame on standard output, numbered from the init frame; then a
    // later init frame.
    let o = common::ok(&on_video(&["--jsonl", "--init-frame", "5"]));
    let objs: Vec<serde_json::Value> = o.lines().map(|l| serde_json::from_str(l).unwrap()).collect();
    assert_eq!(objs.len(), n - 5);
    assert_eq!(objs[0]["frame"], 5);
    assert_eq!(objs[0]["score"], 1.0);
    assert!(objs.iter().all(|o| o["box"].as_array().unwrap().len() == 4 && o["time_s"].as_f64().is_some()));
    // --vis-video: the video with the boxes, every frame, put in place at the end.
    let vis = tmp.path().join("boxes.mkv");
    common::ok(&on_video(&["--vis-video", &s(&vis), "--max-frames", "8"]));
    let probe = Command::new("ffprobe")
        .args(["-v", "error", "-count_frames", "-select_streams", "v:0", "-show_entries", "stream=nb_read_frames"])
        .args(["-of", "csv=p=0"])
        .arg(&vis)
        .output()
        .unwrap();
    assert_eq!(String::from_utf8_lossy(&probe.stdout).trim(), "8");
    let leftovers = std::fs::read_dir(tmp.path())
        .unwrap()
        .filter(|e| e.as_ref().unwrap().file_name().to_string_lossy().starts_with(".tmp-"));
    assert_eq!(leftovers.count(), 0, "no temporary file left");
    // Not a video: one line, naming it.
    let junk = tmp.path().join("junk.mkv");
    std::fs::write(&junk, vec![7u8; 5000]).unwrap();
    let o = common::prl(&["track", "--plan", &s(&plan), "--video", &s(&junk), "--init", &init]);
    let err = String::from_utf8_lossy(&o.stderr);
    assert!(!o.status.success() && err.trim().lines().count() == 1 && err.contains("junk.mkv"), "{err}");
    // A missing file: one line, naming it.
    let o = common::prl(&["track", "--plan", &s(&plan), "--video", "/nonexistent/v.mkv", "--init", &init]);
    let err = String::from_utf8_lossy(&o.stderr);
    assert!(!o.status.success() && err.trim().lines().count() == 1 && err.contains("/nonexistent/v.mkv"), "{err}");
    // A camera device that is not there (FFmpeg's V4L2 input): one line, naming it. (No camera
    // is at hand on CI's machines, so this is as far as the device path is tested.)
    let cam = "/dev/video99";
    if !Path::new(cam).exists() {
        let o = common::prl(&["track", "--plan", &s(&plan), "--video", cam, "--init", &init]);
        let err = String::from_utf8_lossy(&o.stderr);
        assert!(!o.status.success() && err.trim().lines().count() == 1 && err.contains(cam), "{err}");
    }
}

#[test]
fn live_pacing_drops_frames_and_counts_them() {
    if !have_ffmpeg() {
        return;
    }
    // A 320x240 source that decodes far faster than PRL-Track's step.
    let tmp = tempfile::tempdir().unwrap();
    let video = tmp.path().join("fast.mkv");
    let (w, h, n) = (320, 240, 120);
    encode(&video, w, h, stripes(w, h, n));
    let s = |p: &Path| p.to_str().unwrap().to_string();
    let results = tmp.path().join("live.txt");
    let out = common::ok(&common::prl(&[
        "track",
        "--plan",
        &s(&common::reference_plan()),
        "--video",
        &s(&video),
        "--init",
        "100,80,60,50",
        "--live",
        "--threads",
        "1",
        "--results",
        &s(&results),
    ]));
    let line = out.lines().find(|l| l.starts_with("frames: ")).unwrap();
    let nums: Vec<usize> = line.split_whitespace().filter_map(|w| w.parse().ok()).take(2).collect();
    let (tracked, dropped) = (nums[0], nums[1]);
    assert!(dropped > 0 && tracked + dropped <= n, "{line}");
    // Each result carries its frame number, increasing; together with the dropped ones they
    // account for every frame up to the last tracked one.
    let frames: Vec<usize> = std::fs::read_to_string(&results)
        .unwrap()
        .lines()
        .map(|l| l.split(',').next().unwrap().parse().unwrap())
        .collect();
    assert_eq!(frames.len(), tracked);
    assert!(frames.windows(2).all(|p| p[0] < p[1]), "{frames:?}");
    assert_eq!(frames[0], 0);
    assert_eq!(*frames.last().unwrap() + 1, tracked + dropped, "{frames:?} {line}");
}

/// The pids of `pid`'s child processes named `name` (from `/proc`).
fn children_named(pid: u32, name: &str) -> Vec<i32> {
    let Ok(rd) = std::fs::read_dir("/proc") else { return vec![] };
    rd.filter_map(|e| e.ok()?.file_name().to_str()?.parse::<i32>().ok())
        .filter(|p| {
            let stat = std::fs::read_to_string(format!("/proc/{p}/stat")).unwrap_or_default();
            // `pid (comm) state ppid ...`; comm may hold spaces, so split after its `)`.
            let (comm, rest) = (stat.split(['(', ')']).nth(1).unwrap_or(""), stat.rsplit(')').next().unwrap_or(""));
            comm == name && rest.split_whitespace().nth(1) == Some(&pid.to_string())
        })
        .collect()
}

/// A stream that breaks mid-way (the decoder killed, as when a link drops): a one-line error
/// naming the source, after the frames that came; a file cut short: the frames before the cut,
/// tracked as in the whole file, and the run ends cleanly.
#[test]
fn a_stream_that_breaks_or_a_file_cut_short() {
    if !have_ffmpeg() {
        return;
    }
    let tmp = tempfile::tempdir().unwrap();
    let plan = common::nanotrack_plan(tmp.path());
    let video = tmp.path().join("long.mkv");
    let (w, h, n) = (320, 240, 300);
    encode(&video, w, h, stripes(w, h, n));
    let s = |p: &Path| p.to_str().unwrap().to_string();
    let args = |v: &Path| {
        ["track", "--plan", &s(&plan), "--video", &s(v), "--init", "100,80,60,50", "--jsonl"].map(String::from)
    };
    let mut child = Command::new(env!("CARGO_BIN_EXE_prl"))
        .args(args(&video))
        .stdout(Stdio::piped())
        .stderr(Stdio::piped())
        .spawn()
        .unwrap();
    let mut lines = std::io::BufRead::lines(std::io::BufReader::new(child.stdout.take().unwrap()));
    for _ in 0..3 {
        lines.next().unwrap().unwrap();
    }
    let ffmpeg = children_named(child.id(), "ffmpeg");
    assert_eq!(ffmpeg.len(), 1, "one ffmpeg decoding for prl");
    // SAFETY: kill(2) on a pid just read from /proc; the worst case is a signal to nothing.
    assert_eq!(unsafe { libc::kill(ffmpeg[0], libc::SIGKILL) }, 0);
    let seen = 3 + lines.count();
    let o = child.wait_with_output().unwrap();
    let err = String::from_utf8_lossy(&o.stderr);
    let last = err.trim().lines().last().unwrap_or("");
    assert_eq!(o.status.code(), Some(1), "{err}");
    assert!(last.starts_with("error: ") && last.contains("long.mkv") && last.contains("signal"), "{err}");
    assert!(seen < n, "{seen} frames before the break");

    // The file cut in half: what is before the cut tracks as in the whole file.
    let whole = common::ok(&common::prl(&args(&video).iter().map(String::as_str).collect::<Vec<_>>()));
    let bytes = std::fs::read(&video).unwrap();
    let cut = tmp.path().join("cut.mkv");
    std::fs::write(&cut, &bytes[..bytes.len() / 2]).unwrap();
    let o = common::prl(&args(&cut).iter().map(String::as_str).collect::<Vec<_>>());
    let part = common::ok(&o);
    let (whole, part): (Vec<&str>, Vec<&str>) = (whole.lines().collect(), part.lines().collect());
    assert_eq!(whole.len(), n);
    assert!(part.len() > 10 && part.len() < n, "{} frames of the cut file", part.len());
    let boxes = |l: &&str| serde_json::from_str::<serde_json::Value>(l).unwrap()["box"].clone();
    assert!(part.iter().zip(&whole).all(|(a, b)| boxes(a) == boxes(b)), "the frames before the cut track alike");
}

/// A network stream (MPEG-TS over UDP on loopback, as drone links send it: the size comes only
/// with the stream's own headers, and UDP has no end): tracked live from the one connection
/// `prl` opens, until Ctrl-C, which ends the run cleanly with every tracked frame's result
/// written.
#[test]
fn a_udp_stream_tracks_live_until_ctrl_c() {
    if !have_ffmpeg() {
        return;
    }
    let tmp = tempfile::tempdir().unwrap();
    let plan = common::nanotrack_plan(tmp.path());
    let video = tmp.path().join("src.mkv");
    let (w, h) = (320, 240);
    encode(&video, w, h, stripes(w, h, 50));
    let port = std::net::UdpSocket::bind("127.0.0.1:0").unwrap().local_addr().unwrap().port();
    let url = format!("udp://127.0.0.1:{port}");
    // The sender: the file looped at its own pace (10 fps), MPEG-2 with headers on every GOP.
    let mut sender = Command::new("ffmpeg")
        .args(["-hide_banner", "-loglevel", "error", "-re", "-stream_loop", "-1", "-i"])
        .arg(&video)
        .args(["-c:v", "mpeg2video", "-g", "5", "-q:v", "2", "-f", "mpegts"])
        .arg(format!("{url}?pkt_size=1316"))
        .stdin(Stdio::null())
        .spawn()
        .unwrap();
    let results = tmp.path().join("stream.txt");
    let (mut child, watchdog) = track_live(&plan, &url, "100,80,60,50", &results);
    let pid = child.id() as i32;
    let mut lines = std::io::BufRead::lines(std::io::BufReader::new(child.stdout.take().unwrap()));
    let mut objs = vec![];
    for _ in 0..8 {
        let line = lines.next().expect("a frame from the stream within 90 s").unwrap();
        objs.push(serde_json::from_str::<serde_json::Value>(&line).unwrap());
    }
    // SAFETY: kill(2) on our running child's pid: Ctrl-C.
    assert_eq!(unsafe { libc::kill(pid, libc::SIGINT) }, 0);
    objs.extend(lines.map(|l| serde_json::from_str::<serde_json::Value>(&l.unwrap()).unwrap()));
    let o = child.wait_with_output().unwrap();
    watchdog.disarm();
    let _ = sender.kill();
    let _ = sender.wait();
    let err = String::from_utf8_lossy(&o.stderr);
    assert!(o.status.success(), "{err}");
    assert!(err.contains("video: udp://127.0.0.1") && err.contains(&format!("{w}x{h}")), "{err}");
    assert!(err.contains("stopped on request"), "{err}");
    // Every frame tracked is in the results, with its frame number, increasing.
    let text = std::fs::read_to_string(&results).unwrap();
    let numbers: Vec<u64> = text.lines().map(|l| l.split(',').next().unwrap().parse().unwrap()).collect();
    let tracked: Vec<u64> = objs.iter().map(|o| o["frame"].as_u64().unwrap()).collect();
    assert_eq!(numbers, tracked);
    assert!(tracked.len() >= 8 && tracked.windows(2).all(|p| p[0] < p[1]), "{tracked:?}");
}

/// The watchdog of [`track_live`]; disarm it once the child is reaped (a test that fails before
/// leaves it armed, and the child is killed).
struct Watchdog(std::sync::Arc<std::sync::atomic::AtomicBool>);

impl Watchdog {
    fn disarm(self) {
        self.0.store(true, std::sync::atomic::Ordering::SeqCst);
    }
}

/// `prl track --live --jsonl` on one thread from `url`, starting at `init`, results to `results`;
/// killed if it still runs after 90 s, so that a stream that never arrives or never ends fails
/// the test rather than hanging it.
fn track_live(plan: &Path, url: &str, init: &str, results: &Path) -> (std::process::Child, Watchdog) {
    let s = |p: &Path| p.to_str().unwrap().to_string();
    let child = Command::new(env!("CARGO_BIN_EXE_prl"))
        .args(["track", "--plan", &s(plan), "--video", url, "--init", init, "--live", "--jsonl"])
        .args(["--threads", "1", "--results", &s(results)])
        .stdout(Stdio::piped())
        .stderr(Stdio::piped())
        .spawn()
        .unwrap();
    let pid = child.id() as i32;
    let done = std::sync::Arc::new(std::sync::atomic::AtomicBool::new(false));
    let watched = std::sync::Arc::clone(&done);
    std::thread::spawn(move || {
        std::thread::sleep(std::time::Duration::from_secs(90));
        if !watched.load(std::sync::atomic::Ordering::SeqCst) {
            // SAFETY: kill(2) on the child's pid, not reaped yet: the caller disarms the
            // watchdog only after waiting for the child.
            unsafe { libc::kill(pid, libc::SIGKILL) };
        }
    });
    (child, Watchdog(done))
}

/// A Python that has GStreamer's RTSP server (`scripts/rtsp-server.py`): the system's first, as
/// its packages install there (a pyenv or venv `python3` may come first on the PATH).
fn rtsp_server_python() -> Option<&'static str> {
    let check = "import gi; gi.require_version('GstRtspServer', '1.0'); from gi.repository import GstRtspServer";
    let found = ["/usr/bin/python3", "python3"]
        .into_iter()
        .find(|py| Command::new(py).args(["-c", check]).stderr(Stdio::null()).status().is_ok_and(|s| s.success()));
    if found.is_none() {
        eprintln!(
            "NOTE: GStreamer's RTSP server not found: the RTSP test is NOT run here (sudo apt-get install \
             python3-gi gir1.2-gst-rtsp-server-1.0 gstreamer1.0-plugins-good gstreamer1.0-plugins-bad)"
        );
    }
    found
}

/// An RTSP camera, as a drone link delivers one: building4's first 40 frames as H.264 served in
/// real time by GStreamer's RTSP server. `prl track --live` tracks it from the first frame it
/// gets until the stream ends, which ends the run cleanly with the results written, and stays
/// on the target.
#[test]
fn an_rtsp_camera_tracks_live_until_its_stream_ends() {
    if !have_ffmpeg() {
        return;
    }
    let Some(python) = rtsp_server_python() else { return };
    let tmp = tempfile::tempdir().unwrap();
    let plan = common::nanotrack_plan(tmp.path());
    let seq = common::sequence("building4");
    let video = tmp.path().join("building4.mp4");
    let encoded = Command::new("ffmpeg")
        .args(["-hide_banner", "-loglevel", "error", "-framerate", "10", "-i"])
        .arg(seq.join("img/%06d.jpg"))
        .args(["-frames:v", "40", "-c:v", "libx264", "-preset", "ultrafast", "-g", "10", "-pix_fmt", "yuv420p"])
        .arg(&video)
        .status()
        .unwrap();
    assert!(encoded.success());
    let port = std::net::TcpListener::bind("127.0.0.1:0").unwrap().local_addr().unwrap().port();
    let script = Path::new(env!("CARGO_MANIFEST_DIR")).join("scripts/rtsp-server.py");
    let mut server =
        Command::new(python).arg(&script).arg(&video).arg(port.to_string()).stdout(Stdio::piped()).spawn().unwrap();
    let mut said = String::new();
    std::io::BufRead::read_line(&mut std::io::BufReader::new(server.stdout.take().unwrap()), &mut said).unwrap();
    let url = format!("rtsp://127.0.0.1:{port}/cam");
    assert_eq!(said.trim(), format!("serving {url}"));
    let gt = prl_track::parse_boxes(&seq.join("groundtruth_rect.txt"), 10_000).unwrap();
    let init = gt[0].map(|v| v.to_string()).join(",");
    let results = tmp.path().join("camera.txt");
    let (child, watchdog) = track_live(&plan, &url, &init, &results);
    let o = child.wait_with_output().unwrap();
    watchdog.disarm();
    let _ = server.kill();
    let _ = server.wait();
    let err = String::from_utf8_lossy(&o.stderr);
    assert!(o.status.success(), "{err}");
    assert!(err.contains(&format!("video: {url}, 1280x720, live")), "{err}");
    let objs: Vec<serde_json::Value> =
        String::from_utf8_lossy(&o.stdout).lines().map(|l| serde_json::from_str(l).unwrap()).collect();
    let frames: Vec<usize> = objs.iter().map(|o| o["frame"].as_u64().unwrap() as usize).collect();
    // Live: frames may be dropped, never reordered; the first is the init frame.
    assert!(frames.len() >= 5 && frames[0] == 0 && frames.windows(2).all(|p| p[0] < p[1]), "{frames:?}");
    assert!(*frames.last().unwrap() < 40, "{frames:?}");
    let text = std::fs::read_to_string(&results).unwrap();
    assert_eq!(text.lines().count(), frames.len());
    // On the target: H.264 at its defaults and dropped frames, and still over the ground truth.
    let boxes = objs.iter().map(|o| {
        let b: Vec<f64> = o["box"].as_array().unwrap().iter().map(|v| v.as_f64().unwrap()).collect();
        [b[0], b[1], b[2], b[3]]
    });
    let mean = boxes.zip(&frames).map(|(b, &f)| prl_track::iou(b, gt[f])).sum::<f64>() / frames.len() as f64;
    assert!(mean > 0.5, "mean IoU {mean} over frames {frames:?}");
}

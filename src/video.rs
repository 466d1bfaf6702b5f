//! Video files, camera devices and streams as frames for the tracker, decoded by FFmpeg: the
//! `ffprobe` program reads the size, the `ffmpeg` program decodes and writes raw BGR frames to a
//! pipe (install: `sudo apt-get install ffmpeg` on Debian, Ubuntu and the Jetson's L4T).
//!
//! Two pacings: [`Pacing::Every`] hands over every frame in order (files: results line up with
//! frame numbers); [`Pacing::Live`] reads the pipe on a thread of its own and hands over the
//! newest frame only, counting the ones it dropped while the tracker was busy (cameras and
//! streams, where waiting would fall behind the scene).

use std::io::Read;
use std::process::{Child, ChildStdout, Command, Stdio};
use std::sync::{Arc, Condvar, Mutex};
use std::time::{Duration, Instant};

use prl_runtime::Frame;

/// Frames larger than this (per side) are refused before anything is allocated.
pub const MAX_SIDE: usize = 16384;

/// How frames are handed over.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Pacing {
    /// Every frame, in order.
    Every,
    /// The newest frame; older ones not yet taken are dropped.
    Live,
}

/// What went wrong with a video source; the message names the source.
#[derive(Debug, thiserror::Error)]
#[error("{src}: {msg}")]
pub struct VideoError {
    /// The source as given.
    pub src: String,
    /// What is wrong, one line.
    pub msg: String,
}

/// One decoded frame of a source.
#[derive(Debug, Clone)]
pub struct VideoFrame {
    /// Its number in the source, from 0.
    pub index: usize,
    /// When it was read, from the start of decoding.
    pub time: Duration,
    /// Its pixels.
    pub frame: Frame,
}

/// A video file, camera device or stream being decoded.
pub struct VideoSource {
    src: String,
    width: usize,
    height: usize,
    child: Child,
    reader: Reader,
    /// The first frame handed over.
    first: usize,
    /// Frames dropped so far (live pacing).
    dropped: usize,
    last_index: Option<usize>,
}

enum Reader {
    Every { pipe: ChildStdout, next: usize, start: Instant },
    Live { slot: Arc<(Mutex<Slot>, Condvar)> },
}

/// The newest frame read by the live reader, and how the pipe ended.
#[derive(Default)]
struct Slot {
    frame: Option<(usize, Duration, Vec<u8>)>,
    ended: Option<Result<(), ReadFailure>>,
}

/// FFmpeg's (and ffprobe's) input options for a source: a V4L2 device for `/dev/video*`, else what FFmpeg
/// detects (files, `rtsp://`, `udp://`, `http://` ...).
fn input_args(src: &str) -> Vec<String> {
    let mut v = vec![];
    if src.starts_with("/dev/video") {
        v.extend(["-f".to_string(), "v4l2".to_string()]);
    }
    v.extend(["-i".to_string(), src.to_string()]);
    v
}

fn missing_tool(src: &str, tool: &str, e: std::io::Error) -> VideoError {
    let msg = if e.kind() == std::io::ErrorKind::NotFound {
        format!("`{tool}` not found: video input needs FFmpeg (Debian, Ubuntu, Jetson: sudo apt-get install ffmpeg)")
    } else {
        format!("cannot run `{tool}`: {e}")
    };
    VideoError { src: src.to_string(), msg }
}

/// The last non-empty line FFmpeg wrote to its standard error (its reason), or `fallback`.
fn last_line(stderr: &[u8], fallback: &str) -> String {
    let text = String::from_utf8_lossy(stderr);
    text.lines().rev().find(|l| !l.trim().is_empty()).map(|l| l.trim().to_string()).unwrap_or_else(|| fallback.into())
}

impl VideoSource {
    /// Open `src` (a file, `/dev/videoN`, or a stream URL) and start decoding it. Frames before
    /// number `first` are skipped; frame `first` (the one a tracker is initialised on) is always
    /// handed over, live or not.
    pub fn open(src: &str, pacing: Pacing, first: usize) -> Result<VideoSource, VideoError> {
        let err = |msg: String| VideoError { src: src.to_string(), msg };
        let out = Command::new("ffprobe")
            .args(["-v", "error", "-select_streams", "v:0", "-show_entries", "stream=width,height", "-of", "csv=p=0"])
            .args(input_args(src))
            .output()
            .map_err(|e| missing_tool(src, "ffprobe", e))?;
        if !out.status.success() {
            return Err(err(format!("cannot open: {}", last_line(&out.stderr, "ffprobe failed"))));
        }
        let text = String::from_utf8_lossy(&out.stdout);
        let dims: Vec<usize> =
            text.lines().next().unwrap_or("").split(',').filter_map(|v| v.trim().parse().ok()).collect();
        let (width, height) = match dims[..] {
            [w, h, ..] if (1..=MAX_SIDE).contains(&w) && (1..=MAX_SIDE).contains(&h) => (w, h),
            [w, h, ..] => return Err(err(format!("a {w}x{h} video: sides must be 1..={MAX_SIDE}"))),
            _ => return Err(err("no video stream".into())),
        };
        let mut child = Command::new("ffmpeg")
            .args(["-hide_banner", "-loglevel", "error", "-nostdin"])
            .args(input_args(src))
            .args(["-map", "0:v:0", "-f", "rawvideo", "-pix_fmt", "bgr24", "-"])
            .stdin(Stdio::null())
            .stdout(Stdio::piped())
            .stderr(Stdio::piped())
            .spawn()
            .map_err(|e| missing_tool(src, "ffmpeg", e))?;
        let pipe = child.stdout.take().expect("piped");
        let bytes = width * height * 3;
        let reader = match pacing {
            Pacing::Every => Reader::Every { pipe, next: 0, start: Instant::now() },
            Pacing::Live => {
                let slot = Arc::new((Mutex::new(Slot::default()), Condvar::new()));
                let shared = Arc::clone(&slot);
                std::thread::spawn(move || live_reader(pipe, bytes, first, shared));
                Reader::Live { slot }
            }
        };
        Ok(VideoSource { src: src.to_string(), width, height, child, reader, first, dropped: 0, last_index: None })
    }

    /// The frames' width and height.
    pub fn size(&self) -> (usize, usize) {
        (self.width, self.height)
    }

    /// Frames dropped so far (live pacing: read from the source but never handed over).
    pub fn dropped(&self) -> usize {
        self.dropped
    }

    /// The next frame (the newest one, live), or `None` when the source ended cleanly.
    pub fn next_frame(&mut self) -> Result<Option<VideoFrame>, VideoError> {
        let bytes = self.width * self.height * 3;
        let got = match &mut self.reader {
            Reader::Every { pipe, next, start } => loop {
                match read_frame(pipe, bytes) {
                    Ok(Some(buf)) => {
                        *next += 1;
                        if *next > self.first {
                            break Some((*next - 1, start.elapsed(), buf));
                        }
                    }
                    Ok(None) => break None,
                    Err(f) => return Err(self.failure(f)),
                }
            },
            Reader::Live { slot } => {
                let (lock, ready) = &**slot;
                let mut s = lock.lock().expect("reader thread does not panic holding the lock");
                loop {
                    if let Some(f) = s.frame.take() {
                        ready.notify_one();
                        break Some(f);
                    }
                    match &s.ended {
                        Some(Ok(())) => break None,
                        Some(Err(f)) => {
                            let f = f.clone();
                            drop(s);
                            return Err(self.failure(f));
                        }
                        None => s = ready.wait(s).expect("reader thread does not panic holding the lock"),
                    }
                }
            }
        };
        let Some((index, time, buf)) = got else {
            // The source's end: FFmpeg's exit status says whether it ended cleanly.
            return wait_for(&mut self.child, &self.src).map(|()| None);
        };
        self.dropped += index - self.last_index.map_or(self.first, |l| l + 1);
        self.last_index = Some(index);
        let frame = Frame::from_bgr(self.width, self.height, buf)
            .map_err(|e| VideoError { src: self.src.clone(), msg: e.to_string() })?;
        Ok(Some(VideoFrame { index, time, frame }))
    }

    /// A read failure, with FFmpeg's own reason where it gave one. If FFmpeg closed the pipe it
    /// has ended by itself (killed, crashed, or a broken stream): its exit status comes first.
    /// Otherwise it is stopped here, and its status (our own kill) says nothing.
    fn failure(&mut self, f: ReadFailure) -> VideoError {
        if !f.closed {
            let _ = self.child.kill();
        }
        let msg = match wait_for(&mut self.child, &self.src) {
            Err(e) if f.closed => format!("{}; {}", e.msg, f.msg),
            Err(e) if !e.msg.starts_with("ffmpeg exited") => e.msg,
            _ => f.msg,
        };
        VideoError { src: self.src.clone(), msg }
    }
}

impl Drop for VideoSource {
    fn drop(&mut self) {
        let _ = self.child.kill();
        let _ = self.child.wait();
    }
}

/// Wait for FFmpeg to exit: an error with its last line of standard error (its reason) unless it
/// succeeded.
fn wait_for(child: &mut Child, src: &str) -> Result<(), VideoError> {
    let mut stderr = vec![];
    if let Some(mut e) = child.stderr.take() {
        let _ = e.read_to_end(&mut stderr);
    }
    let err = |msg: String| VideoError { src: src.to_string(), msg };
    match child.wait() {
        Ok(s) if s.success() => Ok(()),
        Ok(s) => Err(err(last_line(&stderr, &format!("ffmpeg exited with {s}")))),
        Err(e) => Err(err(format!("ffmpeg: {e}"))),
    }
}

/// Why a frame could not be read from FFmpeg's pipe.
#[derive(Debug, Clone)]
struct ReadFailure {
    msg: String,
    /// FFmpeg closed the pipe (mid-frame): it has ended, and its exit status says why.
    closed: bool,
}

/// One frame of `bytes` from the pipe; `None` at a clean end between frames.
fn read_frame(pipe: &mut impl Read, bytes: usize) -> Result<Option<Vec<u8>>, ReadFailure> {
    let mut buf = vec![0u8; bytes];
    let mut filled = 0;
    while filled < bytes {
        match pipe.read(&mut buf[filled..]) {
            Ok(0) if filled == 0 => return Ok(None),
            Ok(0) => {
                let msg = format!("the stream ended inside a frame ({filled} of {bytes} bytes)");
                return Err(ReadFailure { msg, closed: true });
            }
            Ok(n) => filled += n,
            Err(e) if e.kind() == std::io::ErrorKind::Interrupted => {}
            Err(e) => return Err(ReadFailure { msg: format!("reading ffmpeg's output: {e}"), closed: false }),
        }
    }
    Ok(Some(buf))
}

/// The live reader: keeps only the newest frame in the slot, from frame `first` on (which it
/// never overwrites: the tracker starts on it).
fn live_reader(mut pipe: ChildStdout, bytes: usize, first: usize, slot: Arc<(Mutex<Slot>, Condvar)>) {
    let start = Instant::now();
    let (lock, ready) = &*slot;
    for index in 0.. {
        let got = read_frame(&mut pipe, bytes);
        if index < first && matches!(got, Ok(Some(_))) {
            continue;
        }
        let Ok(mut s) = lock.lock() else { return };
        if index == first + 1 {
            // Wait until the first frame has been taken.
            while s.frame.is_some() {
                let Ok(next) = ready.wait(s) else { return };
                s = next;
            }
        }
        match got {
            Ok(Some(buf)) => s.frame = Some((index, start.elapsed(), buf)),
            Ok(None) => s.ended = Some(Ok(())),
            Err(f) => s.ended = Some(Err(f)),
        }
        let done = s.ended.is_some();
        drop(s);
        ready.notify_one();
        if done {
            return;
        }
    }
}

/// A video written by FFmpeg from BGR frames (the codec is FFmpeg's default for the file's
/// extension, in yuv420p so that players take it), through a temporary file renamed at
/// [`VideoWriter::finish`]: a failed run leaves nothing half-written.
pub struct VideoWriter {
    path: std::path::PathBuf,
    tmp: std::path::PathBuf,
    child: Child,
    stdin: Option<std::process::ChildStdin>,
    bytes: usize,
}

impl VideoWriter {
    /// Start writing `path`: `width` x `height` frames at `fps`.
    pub fn create(path: &std::path::Path, width: usize, height: usize, fps: f64) -> Result<VideoWriter, VideoError> {
        let src = path.display().to_string();
        let err = |msg: String| VideoError { src: src.clone(), msg };
        let name = path.file_name().ok_or_else(|| err("not a file path".into()))?.to_string_lossy().into_owned();
        // The temporary keeps the extension: FFmpeg picks the container from it.
        let tmp = path.with_file_name(format!(".tmp-{}-{name}", std::process::id()));
        let mut child = Command::new("ffmpeg")
            .args(["-hide_banner", "-loglevel", "error", "-y", "-f", "rawvideo", "-pix_fmt", "bgr24", "-s"])
            .arg(format!("{width}x{height}"))
            .args(["-r", &format!("{fps}"), "-i", "-", "-pix_fmt", "yuv420p"])
            .arg(&tmp)
            .stdin(Stdio::piped())
            .stdout(Stdio::null())
            .stderr(Stdio::piped())
            .spawn()
            .map_err(|e| missing_tool(&src, "ffmpeg", e))?;
        let stdin = child.stdin.take();
        Ok(VideoWriter { path: path.to_path_buf(), tmp, child, stdin, bytes: width * height * 3 })
    }

    /// Append one frame (`width * height * 3` BGR bytes).
    pub fn write(&mut self, bgr: &[u8]) -> Result<(), VideoError> {
        let err = |msg: String| VideoError { src: self.path.display().to_string(), msg };
        if bgr.len() != self.bytes {
            return Err(err(format!("a frame of {} bytes; the video's take {}", bgr.len(), self.bytes)));
        }
        use std::io::Write;
        let stdin = self.stdin.as_mut().ok_or_else(|| err("already finished".into()))?;
        stdin.write_all(bgr).map_err(|e| err(format!("ffmpeg stopped taking frames: {e}")))
    }

    /// Close the stream, wait for FFmpeg and put the file in place.
    pub fn finish(mut self) -> Result<(), VideoError> {
        let src = self.path.display().to_string();
        drop(self.stdin.take());
        wait_for(&mut self.child, &src)?;
        prl_runtime::commit(&self.tmp, &self.path).map_err(|e| VideoError {
            src,
            msg: match e {
                prl_runtime::Error::Io { err, .. } => format!("cannot write: {err}"),
                other => other.to_string(),
            },
        })
    }
}

impl Drop for VideoWriter {
    fn drop(&mut self) {
        // Unfinished (an error on the way): stop FFmpeg and remove its partial file.
        if self.stdin.is_some() {
            let _ = self.child.kill();
            let _ = self.child.wait();
        }
        let _ = std::fs::remove_file(&self.tmp);
    }
}

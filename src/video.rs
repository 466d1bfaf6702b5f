//! Video files, camera devices and streams as frames for the tracker, decoded by FFmpeg: the
//! `ffmpeg` program decodes and writes each frame to a pipe as an uncompressed 24-bit BMP image
//! (BGR pixels behind a header that carries the size), so that the source is opened once: a
//! stream that serves one client, or sends its size only with its keyframes (UDP, RTSP), needs
//! no separate probe (install: `sudo apt-get install ffmpeg` on Debian, Ubuntu and the Jetson's
//! L4T).
//!
//! Two pacings: [`Pacing::Every`] hands over every frame in order (files: results line up with
//! frame numbers); [`Pacing::Live`] reads the pipe on a thread of its own and hands over the
//! newest frame only, counting the ones it dropped while the tracker was busy (cameras and
//! streams, where waiting would fall behind the scene).

use std::io::{BufReader, Read};
use std::process::{Child, ChildStdout, Command, Stdio};
use std::sync::atomic::{AtomicBool, Ordering};
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
    child: Ffmpeg,
    reader: Reader,
    /// The first frame handed over.
    first: usize,
    /// Frames dropped so far (live pacing).
    dropped: usize,
    last_index: Option<usize>,
    /// Set to end the source cleanly at the next frame ([`VideoSource::stop_flag`]).
    stop: Arc<AtomicBool>,
}

/// FFmpeg's frame pipe, buffered: a frame is read row by row into place.
type Pipe = BufReader<ChildStdout>;

enum Reader {
    /// `next`: the number of the frame `pending` holds (the first one, read by `open`), or of
    /// the next one the pipe gives.
    Every {
        pipe: Pipe,
        pending: Option<Vec<u8>>,
        next: usize,
        start: Instant,
    },
    Live {
        slot: Arc<(Mutex<Slot>, Condvar)>,
    },
}

/// The newest frame read by the live reader, and how the pipe ended.
#[derive(Default)]
struct Slot {
    frame: Option<(usize, Duration, Vec<u8>)>,
    ended: Option<Result<(), ReadFailure>>,
}

/// FFmpeg's input options for a source: a V4L2 device for `/dev/video*`, else what FFmpeg
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

/// A running FFmpeg. Its standard error is read as it comes, on a thread of its own, keeping the
/// last 4 KiB (its reason, if it fails): a long run's warnings (a lossy stream's decoding errors)
/// never fill the pipe and stall FFmpeg.
struct Ffmpeg {
    child: Child,
    tail: Arc<Mutex<Vec<u8>>>,
    drain: Option<std::thread::JoinHandle<()>>,
}

impl Ffmpeg {
    /// Start `cmd` (its standard error piped here), naming `src` if the program is missing.
    fn spawn(cmd: &mut Command, src: &str) -> Result<Ffmpeg, VideoError> {
        let mut child = cmd.stderr(Stdio::piped()).spawn().map_err(|e| missing_tool(src, "ffmpeg", e))?;
        let tail = Arc::new(Mutex::new(Vec::new()));
        let (mut stderr, kept) = (child.stderr.take().expect("piped"), Arc::clone(&tail));
        let drain = std::thread::spawn(move || {
            let mut buf = [0u8; 4096];
            while let Ok(n @ 1..) = stderr.read(&mut buf) {
                let Ok(mut t) = kept.lock() else { return };
                t.extend_from_slice(&buf[..n]);
                let excess = t.len().saturating_sub(4096);
                t.drain(..excess);
            }
        });
        Ok(Ffmpeg { child, tail, drain: Some(drain) })
    }

    /// Stop it (it may have ended already).
    fn kill(&mut self) {
        let _ = self.child.kill();
    }

    /// Wait for it to exit: an error with its last line of standard error (its reason) unless
    /// it succeeded.
    fn wait(&mut self, src: &str) -> Result<(), VideoError> {
        let err = |msg: String| VideoError { src: src.to_string(), msg };
        let status = self.child.wait();
        if let Some(d) = self.drain.take() {
            let _ = d.join();
        }
        let tail = self.tail.lock().map(|t| t.clone()).unwrap_or_default();
        match status {
            Ok(s) if s.success() => Ok(()),
            Ok(s) => Err(err(last_line(&tail, &format!("ffmpeg exited with {s}")))),
            Err(e) => Err(err(format!("ffmpeg: {e}"))),
        }
    }
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
        let mut child = Ffmpeg::spawn(
            Command::new("ffmpeg")
                .args(["-hide_banner", "-loglevel", "error", "-nostdin"])
                .args(input_args(src))
                .args(["-map", "0:v:0", "-f", "image2pipe", "-c:v", "bmp", "-pix_fmt", "bgr24", "-"])
                .stdin(Stdio::null())
                .stdout(Stdio::piped()),
            src,
        )?;
        let mut pipe = BufReader::with_capacity(1 << 20, child.child.stdout.take().expect("piped"));
        let start = Instant::now();
        // The first frame gives the size; a source that gives none is an error with FFmpeg's
        // reason (a missing file, an unsupported codec, a stream that is not there).
        let first_frame = match read_frame(&mut pipe, None) {
            Ok(Some(f)) => f,
            Ok(None) => {
                let reason = child.wait(src).err().map_or("no video frame".into(), |e| e.msg);
                return Err(err(format!("cannot open: {reason}")));
            }
            Err(f) => {
                child.kill();
                let reason = child.wait(src).err().map_or(f.msg, |e| e.msg);
                return Err(err(format!("cannot open: {reason}")));
            }
        };
        let (width, height) = (first_frame.width, first_frame.height);
        let reader = match pacing {
            Pacing::Every => Reader::Every { pipe, pending: Some(first_frame.bgr), next: 0, start },
            Pacing::Live => {
                let slot = Arc::new((Mutex::new(Slot::default()), Condvar::new()));
                let shared = Arc::clone(&slot);
                std::thread::spawn(move || live_reader(pipe, first_frame, first, start, shared));
                Reader::Live { slot }
            }
        };
        let stop = Arc::new(AtomicBool::new(false));
        Ok(VideoSource {
            src: src.to_string(),
            width,
            height,
            child,
            reader,
            first,
            dropped: 0,
            last_index: None,
            stop,
        })
    }

    /// A flag that ends the source cleanly when set (from another thread or a signal handler,
    /// as `prl track --video` does on Ctrl-C): [`VideoSource::next_frame`] then gives `None`, as
    /// at the end of a file, so that a live stream, which has no end of its own, ends a run
    /// with its results. A live source sees it within 0.1 s; with every frame, at the next frame.
    pub fn stop_flag(&self) -> Arc<AtomicBool> {
        Arc::clone(&self.stop)
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
        let stopped = || self.stop.load(Ordering::SeqCst);
        if stopped() {
            return Ok(None);
        }
        let size = (self.width, self.height);
        let got = match &mut self.reader {
            Reader::Every { pipe, pending, next, start } => loop {
                let read = match pending.take() {
                    Some(buf) => Ok(Some(buf)),
                    None => read_frame(pipe, Some(size)).map(|f| f.map(|f| f.bgr)),
                };
                match read {
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
                    if stopped() {
                        return Ok(None);
                    }
                    match &s.ended {
                        Some(Ok(())) => break None,
                        Some(Err(f)) => {
                            let f = f.clone();
                            drop(s);
                            return Err(self.failure(f));
                        }
                        None => {
                            let wait = ready.wait_timeout(s, Duration::from_millis(100));
                            s = wait.expect("reader thread does not panic holding the lock").0;
                        }
                    }
                }
            }
        };
        let Some((index, time, buf)) = got else {
            // The source's end: FFmpeg's exit status says whether it ended cleanly.
            return self.child.wait(&self.src).map(|()| None);
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
            self.child.kill();
        }
        let msg = match self.child.wait(&self.src) {
            Err(e) if f.closed => format!("{}; {}", e.msg, f.msg),
            Err(e) if !e.msg.starts_with("ffmpeg exited") => e.msg,
            _ => f.msg,
        };
        VideoError { src: self.src.clone(), msg }
    }
}

impl Drop for VideoSource {
    fn drop(&mut self) {
        self.child.kill();
        let _ = self.child.wait(&self.src);
    }
}

/// Why a frame could not be read from FFmpeg's pipe.
#[derive(Debug, Clone)]
struct ReadFailure {
    msg: String,
    /// FFmpeg closed the pipe (mid-frame): it has ended, and its exit status says why.
    closed: bool,
}

/// One frame from FFmpeg's pipe: its size and its BGR pixels, top row first.
struct PipeFrame {
    width: usize,
    height: usize,
    bgr: Vec<u8>,
}

/// The BMP file and info headers (`BITMAPINFOHEADER`) FFmpeg's `bmp` encoder writes.
const BMP_HEADER: usize = 54;

/// Fill `buf` from the pipe. `Ok(false)`: the pipe ended before the first byte, where
/// `at_start` allows it (a clean end between frames).
fn fill(pipe: &mut impl Read, buf: &mut [u8], at_start: bool) -> Result<bool, ReadFailure> {
    let mut filled = 0;
    while filled < buf.len() {
        match pipe.read(&mut buf[filled..]) {
            Ok(0) if filled == 0 && at_start => return Ok(false),
            Ok(0) => {
                let msg = "the stream ended inside a frame".to_string();
                return Err(ReadFailure { msg, closed: true });
            }
            Ok(n) => filled += n,
            Err(e) if e.kind() == std::io::ErrorKind::Interrupted => {}
            Err(e) => return Err(ReadFailure { msg: format!("reading ffmpeg's output: {e}"), closed: false }),
        }
    }
    Ok(true)
}

/// One 24-bit BMP frame from the pipe, its rows read straight into place (BMP stores them bottom
/// up, each padded to 4 bytes); `None` at a clean end between frames. The header is checked
/// before the frame is allocated; `size`: the size every frame after the first must have.
fn read_frame(pipe: &mut impl Read, size: Option<(usize, usize)>) -> Result<Option<PipeFrame>, ReadFailure> {
    let mut head = [0u8; BMP_HEADER];
    if !fill(pipe, &mut head, true)? {
        return Ok(None);
    }
    let le32 = |i: usize| u32::from_le_bytes([head[i], head[i + 1], head[i + 2], head[i + 3]]);
    let le16 = |i: usize| u16::from_le_bytes([head[i], head[i + 1]]);
    let bad = |msg: String| ReadFailure { msg: format!("ffmpeg's frame pipe: {msg}"), closed: false };
    if &head[..2] != b"BM" || le32(14) < 40 || le16(28) != 24 || le32(30) != 0 {
        return Err(bad("not an uncompressed 24-bit BMP frame".into()));
    }
    let (w, h) = (le32(18) as i32, le32(22) as i32);
    let (width, height) = (w.unsigned_abs() as usize, h.unsigned_abs() as usize);
    if !(1..=MAX_SIDE).contains(&width) || !(1..=MAX_SIDE).contains(&height) {
        return Err(bad(format!("a {width}x{height} frame: sides must be 1..={MAX_SIDE}")));
    }
    if let Some((sw, sh)) = size.filter(|&s| s != (width, height)) {
        return Err(bad(format!("the frame size changed from {sw}x{sh} to {width}x{height}")));
    }
    let offset = le32(10) as usize;
    if !(BMP_HEADER..=BMP_HEADER + 1024).contains(&offset) {
        return Err(bad(format!("pixels at byte {offset}")));
    }
    // The bytes between the header and the pixels (checked above: at most 1024), then each
    // row's padding (at most 3).
    let mut skip = [0u8; 1024];
    fill(pipe, &mut skip[..offset - BMP_HEADER], false)?;
    let row = width * 3;
    let pad = row.next_multiple_of(4) - row;
    let mut bgr = vec![0u8; row * height];
    for i in 0..height {
        let y = if h > 0 { height - 1 - i } else { i };
        fill(pipe, &mut bgr[y * row..(y + 1) * row], false)?;
        fill(pipe, &mut skip[..pad], false)?;
    }
    Ok(Some(PipeFrame { width, height, bgr }))
}

/// The live reader: keeps only the newest frame in the slot, from frame `first` on (which it
/// never overwrites: the tracker starts on it). `frame0`: the first frame, read by `open`.
fn live_reader(mut pipe: Pipe, frame0: PipeFrame, first: usize, start: Instant, slot: Arc<(Mutex<Slot>, Condvar)>) {
    let (lock, ready) = &*slot;
    let size = Some((frame0.width, frame0.height));
    let mut frame0 = Some(frame0.bgr);
    for index in 0.. {
        let got = match frame0.take() {
            Some(buf) => Ok(Some(buf)),
            None => read_frame(&mut pipe, size).map(|f| f.map(|f| f.bgr)),
        };
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
    child: Ffmpeg,
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
        let mut child = Ffmpeg::spawn(
            Command::new("ffmpeg")
                .args(["-hide_banner", "-loglevel", "error", "-y", "-f", "rawvideo", "-pix_fmt", "bgr24", "-s"])
                .arg(format!("{width}x{height}"))
                .args(["-r", &format!("{fps}"), "-i", "-", "-pix_fmt", "yuv420p"])
                .arg(&tmp)
                .stdin(Stdio::piped())
                .stdout(Stdio::null()),
            &src,
        )?;
        let stdin = child.child.stdin.take();
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
        self.child.wait(&src)?;
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
            self.child.kill();
            let _ = self.child.wait("");
        }
        let _ = std::fs::remove_file(&self.tmp);
    }
}

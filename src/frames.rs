//! Decoding frames as OpenCV's `imread(IMREAD_COLOR)` does: JPEG with libjpeg-turbo's decoder
//! (mozjpeg; other decoders differ on ~10% of pixels), everything else with `image`; grey and
//! 16-bit images are converted to 8-bit colour.
//!
//! A frame's declared size is checked before its pixels are allocated ([`MAX_FRAME_PIXELS`]).
//! A JPEG that libjpeg decodes with a warning (cut short, or with corrupt entropy data) is
//! *damaged*: OpenCV returns such frames (the missing part grey) and so do we, with a warning
//! naming the frame, unless the caller refuses damaged frames ([`Damaged::Refuse`]).

use std::cell::RefCell;
use std::path::Path;

use mozjpeg_sys::jpeg_common_struct;
use prl_runtime::Frame;

use crate::InputError;

/// The most pixels a frame may declare (8192 x 8192): a header asking for more is refused before
/// anything is allocated.
pub const MAX_FRAME_PIXELS: u64 = 1 << 26;

/// The longest frame file read (512 MiB: an 8192 x 8192 frame stored without compression takes
/// 192 MiB as RGB, 512 MiB as 16-bit RGBA); a longer one is refused before it is read.
pub const MAX_FRAME_FILE_BYTES: u64 = 512 << 20;

/// What to do with a frame the decoder could only partly read.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub enum Damaged {
    /// Use it (as OpenCV does) and print a warning naming the frame on standard error.
    #[default]
    Warn,
    /// Make it an error (`--strict`).
    Refuse,
}

/// Read and decode one frame; a damaged one is used with a warning ([`Damaged::Warn`]).
pub fn load_frame(path: &Path) -> Result<Frame, InputError> {
    read_frame(path, Damaged::Warn)
}

/// Read and decode one frame, taking a damaged one as `damaged` says.
pub fn read_frame(path: &Path, damaged: Damaged) -> Result<Frame, InputError> {
    let (frame, damage) = decode_frame(path)?;
    if let Some(what) = damage {
        match damaged {
            Damaged::Refuse => return Err(InputError::new(path, format!("damaged frame: {what}"))),
            Damaged::Warn => eprintln!("warning: {}: damaged frame ({what}); decoded as OpenCV does", path.display()),
        }
    }
    Ok(frame)
}

/// Read and decode one frame: the frame and, if the decoder had to make up part of it, what it
/// said (libjpeg's warning, e.g. "Premature end of JPEG file").
pub fn decode_frame(path: &Path) -> Result<(Frame, Option<String>), InputError> {
    let bytes = crate::read_bounded(path, MAX_FRAME_FILE_BYTES, "a frame")?;
    decode_frame_bytes(path, &bytes)
}

/// The width and height a frame's header declares (`bytes` as [`decode_frame_bytes`] takes
/// them), read without decoding its pixels; a size over [`MAX_FRAME_PIXELS`] is an error.
pub fn frame_size(path: &Path, bytes: &[u8]) -> Result<(usize, usize), InputError> {
    let bad = |msg: String| InputError::new(path, msg);
    if bytes.starts_with(&[0xff, 0xd8]) {
        let (w, h, _, _) = run_jpeg(bytes, false).map_err(|m| bad(format!("bad JPEG: {m}")))?;
        return Ok((w, h));
    }
    let reader = image::ImageReader::new(std::io::Cursor::new(bytes))
        .with_guessed_format()
        .map_err(|e| bad(format!("cannot read frame: {e}")))?;
    let (w, h) = reader.into_dimensions().map_err(|e| bad(format!("cannot read the image's size: {e}")))?;
    if w == 0 || h == 0 || w as u64 * h as u64 > MAX_FRAME_PIXELS {
        return Err(bad(format!("declares {w}x{h} pixels (at most {MAX_FRAME_PIXELS} are read)")));
    }
    Ok((w as usize, h as usize))
}

/// [`decode_frame`] on bytes already read; `path` names them in errors.
pub fn decode_frame_bytes(path: &Path, bytes: &[u8]) -> Result<(Frame, Option<String>), InputError> {
    let bad = |msg: String| InputError::new(path, msg);
    if bytes.starts_with(&[0xff, 0xd8]) {
        let (w, h, bgr, damage) = decode_jpeg(bytes).map_err(|m| bad(format!("bad JPEG: {m}")))?;
        return Ok((Frame::from_bgr(w, h, bgr).map_err(|e| bad(e.to_string()))?, damage));
    }
    let mut reader = image::ImageReader::new(std::io::Cursor::new(bytes))
        .with_guessed_format()
        .map_err(|e| bad(format!("cannot read frame: {e}")))?;
    let side = MAX_FRAME_PIXELS.isqrt() as u32;
    let mut limits = image::Limits::default();
    limits.max_image_width = Some(side);
    limits.max_image_height = Some(side);
    reader.limits(limits);
    let img = reader.decode().map_err(|e| bad(format!("cannot decode image: {e}")))?;
    let rgb = img.to_rgb8();
    if rgb.width() == 0 || rgb.height() == 0 {
        return Err(bad("empty image".into()));
    }
    Ok((Frame::from_rgb_image(&rgb), None))
}

thread_local! {
    /// libjpeg's first warning during the decode running on this thread.
    static JPEG_WARNING: RefCell<Option<String>> = const { RefCell::new(None) };
}

/// libjpeg's text for the message in `cinfo`.
fn jpeg_message(cinfo: &mut jpeg_common_struct) -> String {
    // SAFETY: `cinfo.err` is the error manager libjpeg is calling us through, set up by
    // `jpeg_std_error`, so it is valid for the call; `format_message` writes at most
    // JMSG_LENGTH_MAX (80) bytes, NUL included, into the buffer it is given. The crate declares
    // the buffer `&[u8; 80]`; it is passed as a pointer to a mutable local, which is what C gets.
    unsafe {
        let Some(err) = cinfo.err.as_ref() else { return "libjpeg error".into() };
        let Some(format) = err.format_message else { return format!("libjpeg message {}", err.msg_code) };
        type Format = unsafe extern "C-unwind" fn(&mut jpeg_common_struct, *mut u8);
        let format: Format = std::mem::transmute(format);
        let mut buf = [0u8; 80];
        format(cinfo, buf.as_mut_ptr());
        let end = buf.iter().position(|&b| b == 0).unwrap_or(buf.len());
        String::from_utf8_lossy(&buf[..end]).into_owned()
    }
}

/// libjpeg's `emit_message`: keep the first warning (level -1), ignore trace messages.
extern "C-unwind" fn note_warning(cinfo: &mut jpeg_common_struct, level: std::os::raw::c_int) {
    if level < 0 {
        let msg = jpeg_message(cinfo);
        JPEG_WARNING.with(|w| {
            w.borrow_mut().get_or_insert(msg);
        });
    }
}

/// libjpeg's `error_exit`: unwind to `decode_jpeg` with the message (mozjpeg-sys is built with
/// unwinding, so libjpeg's frames are unwound through).
extern "C-unwind" fn fail(cinfo: &mut jpeg_common_struct) {
    std::panic::resume_unwind(Box::new(jpeg_message(cinfo)));
}

/// Decode a JPEG to BGR as OpenCV does: width, height, pixels and libjpeg's warning, if any.
fn decode_jpeg(bytes: &[u8]) -> Result<(usize, usize, Vec<u8>, Option<String>), String> {
    let (w, h, px, warning) = run_jpeg(bytes, true)?;
    Ok((w, h, px.unwrap_or_default(), warning))
}

/// Width, height, the BGR pixels if asked for, and libjpeg's warning, if any.
type Jpeg = (usize, usize, Option<Vec<u8>>, Option<String>);

/// libjpeg on `bytes` under this module's error manager: the header (size checked against
/// [`MAX_FRAME_PIXELS`]) and, where `pixels`, the BGR pixels.
fn run_jpeg(bytes: &[u8], pixels: bool) -> Result<Jpeg, String> {
    JPEG_WARNING.with(|w| w.borrow_mut().take());
    // SAFETY: an all-zero `jpeg_error_mgr` is a valid value of the plain C struct (null function
    // pointers, zero counters), and `jpeg_std_error` then fills in libjpeg's defaults.
    let mut err: mozjpeg_sys::jpeg_error_mgr = unsafe { std::mem::zeroed() };
    // SAFETY: `err` is a valid, exclusively borrowed error manager.
    unsafe { mozjpeg_sys::jpeg_std_error(&mut err) };
    err.error_exit = Some(fail);
    err.emit_message = Some(note_warning);
    type Decoded = (usize, usize, Option<Vec<u8>>);
    let decoded = std::panic::catch_unwind(move || -> Result<Decoded, String> {
        let d = mozjpeg::Decompress::builder().with_err(err).from_mem(bytes).map_err(|e| e.to_string())?;
        let (w, h) = (d.width(), d.height());
        if w == 0 || h == 0 || (w as u64) * (h as u64) > MAX_FRAME_PIXELS {
            return Err(format!("declares {w}x{h} pixels (at most {MAX_FRAME_PIXELS} are read)"));
        }
        if !pixels {
            return Ok((w, h, None));
        }
        let mut d = d.to_colorspace(mozjpeg::ColorSpace::JCS_EXT_BGR).map_err(|e| e.to_string())?;
        let px = d.read_scanlines::<u8>().map_err(|e| e.to_string())?;
        d.finish().map_err(|e| e.to_string())?;
        Ok((w, h, Some(px)))
    })
    .unwrap_or_else(|p| Err(p.downcast_ref::<String>().cloned().unwrap_or_else(|| "decoder failure".into())));
    let warning = JPEG_WARNING.with(|w| w.borrow_mut().take());
    let (w, h, px) = decoded?;
    Ok((w, h, px, warning))
}

//! Soak runs: a tracker on a long loop of real frames, sampling resident memory, open file
//! descriptors and the per-frame time, to show that an unattended camera's process neither
//! grows nor slows. The sequence is played forwards then backwards (so the target moves
//! continuously), each frame decoded again as a camera decodes it; nothing per frame is kept.

use std::path::PathBuf;
use std::time::Instant;

use prl_runtime::{BBox, Tracker};

use crate::tracking::TrackError;
use crate::{read_frame, Damaged};

/// One sample, taken after `frame` frames.
#[derive(Debug, Clone, Copy, PartialEq, serde::Serialize)]
pub struct SoakSample {
    /// Frames tracked so far.
    pub frame: usize,
    /// Resident memory of the process, MB, once the allocator has handed back the pages it
    /// keeps after a free (the memory in use): what is judged.
    pub rss_mb: f64,
    /// Resident memory as the sample found it, MB (what `top` shows): also freed pages the
    /// allocator has not yet returned (mimalloc returns them a second after the free).
    pub rss_held_mb: f64,
    /// Open file descriptors of the process.
    pub fds: usize,
    /// Median ms per frame (decode and track) since the previous sample.
    pub median_ms: f64,
}

/// What a soak run saw.
#[derive(Debug, Clone, PartialEq, serde::Serialize)]
pub struct SoakReport {
    /// Every sample, in order.
    pub samples: Vec<SoakSample>,
    /// Samples before this one are warm-up (allocators and caches settle in the first thousand
    /// or so frames).
    pub warm: usize,
    /// Growth of resident memory in use after warm-up: the peak of the later half of the
    /// samples over the peak of the earlier half, minus 1 (0.01: 1%); a leak raises the later
    /// peak.
    pub rss_growth: f64,
    /// Lowest and highest resident memory after warm-up, MB.
    pub rss_range: (f64, f64),
    /// Open descriptors at the last sample minus at the first after warm-up.
    pub fd_growth: i64,
    /// Median ms per frame of the last window over the first one after warm-up.
    pub time_ratio: f64,
    /// Drift of the per-frame time after warm-up: the median of the later half's window
    /// medians over the earlier half's, minus 1 (0.1: 10% slower). Medians of halves, because
    /// a shared machine swings one window by 30%; a tracker that slows as it runs moves them.
    pub time_drift: f64,
}

/// What a soak run must stay within.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct SoakLimits {
    /// Largest resident-memory growth after warm-up (0.02: 2%).
    pub rss: f64,
    /// Largest per-frame time drift after warm-up (0.25: 25%).
    pub time: f64,
}

impl SoakReport {
    /// Whether memory and time stayed within `limits` and no descriptor leaked.
    pub fn holds(&self, limits: SoakLimits) -> bool {
        self.rss_growth <= limits.rss && self.time_drift <= limits.time && self.fd_growth <= 0
    }
}

/// The median of `v` (NaN for none).
fn median(mut v: Vec<f64>) -> f64 {
    v.sort_by(f64::total_cmp);
    v.get(v.len() / 2).copied().unwrap_or(f64::NAN)
}

/// Resident memory of this process in MB (`/proc/self/statm`), if the OS says.
pub fn resident_mb() -> Option<f64> {
    let statm = std::fs::read_to_string("/proc/self/statm").ok()?;
    let pages: f64 = statm.split_whitespace().nth(1)?.parse().ok()?;
    // SAFETY: sysconf only reads a configuration value.
    let page = unsafe { libc::sysconf(libc::_SC_PAGESIZE) };
    Some(pages * page.max(1) as f64 / 1e6)
}

/// Open file descriptors of this process (`/proc/self/fd`), if the OS says.
pub fn open_fds() -> Option<usize> {
    Some(std::fs::read_dir("/proc/self/fd").ok()?.count())
}

/// The `i`-th frame of a forwards-and-backwards loop over `n` frames (0, 1, .., n-1, n-2, .., 1,
/// 0, 1, ..).
fn ping_pong(i: usize, n: usize) -> usize {
    if n < 2 {
        return 0;
    }
    let period = 2 * (n - 1);
    let k = i % period;
    if k < n {
        k
    } else {
        period - k
    }
}

/// Track `total` frames of `frames` looped, from `init` on the first, sampling every `every`
/// frames, the first `warm_up` frames not judged; `on_sample` sees each sample as it is taken.
/// `release_freed` asks the process's allocator to return freed pages to the OS (the binary
/// knows which allocator it links); it is called between the two readings of each sample.
#[allow(clippy::too_many_arguments)]
pub fn soak(
    tracker: &mut Tracker,
    frames: &[PathBuf],
    init: BBox,
    total: usize,
    every: usize,
    warm_up: usize,
    mut release_freed: impl FnMut(),
    mut on_sample: impl FnMut(&SoakSample),
) -> Result<SoakReport, TrackError> {
    let every = every.max(1);
    let mut samples = vec![];
    let mut window: Vec<f64> = Vec::with_capacity(every);
    let first = read_frame(&frames[0], Damaged::Warn)?;
    tracker.init(&first, init).map_err(|source| TrackError::Tracker {
        label: frames[0].display().to_string(),
        target: 0,
        source,
    })?;
    drop(first);
    for i in 1..total.max(2) {
        let t = Instant::now();
        let path = &frames[ping_pong(i, frames.len())];
        let f = read_frame(path, Damaged::Warn)?;
        tracker.track(&f).map_err(|source| TrackError::Tracker {
            label: path.display().to_string(),
            target: 0,
            source,
        })?;
        window.push(t.elapsed().as_secs_f64() * 1e3);
        if (i + 1) % every == 0 || i + 1 == total {
            let rss_held_mb = resident_mb().unwrap_or(f64::NAN);
            release_freed();
            let s = SoakSample {
                frame: i + 1,
                rss_mb: resident_mb().unwrap_or(f64::NAN),
                rss_held_mb,
                fds: open_fds().unwrap_or(0),
                median_ms: median(std::mem::take(&mut window)),
            };
            on_sample(&s);
            samples.push(s);
        }
    }
    let warm = samples.iter().take_while(|s| s.frame <= warm_up).count();
    Ok(summarise(samples, warm))
}

fn summarise(samples: Vec<SoakSample>, warm: usize) -> SoakReport {
    let warm = warm.max(1).min(samples.len().saturating_sub(1));
    let after = &samples[warm.min(samples.len())..];
    let (Some(base), Some(last)) = (after.first(), after.last()) else {
        let (rss_growth, rss_range, fd_growth, time_ratio, time_drift) = (0.0, (0.0, 0.0), 0, 1.0, 0.0);
        return SoakReport { samples, warm, rss_growth, rss_range, fd_growth, time_ratio, time_drift };
    };
    let peak = |s: &[SoakSample]| s.iter().map(|s| s.rss_mb).fold(f64::MIN, f64::max);
    let (earlier, later) = after.split_at(after.len() / 2);
    let rss_growth = if earlier.is_empty() { 0.0 } else { peak(later) / peak(earlier) - 1.0 };
    let low = after.iter().map(|s| s.rss_mb).fold(f64::MAX, f64::min);
    let (rss_range, fd_growth) = ((low, peak(after)), last.fds as i64 - base.fds as i64);
    let time_ratio = last.median_ms / base.median_ms;
    let ms = |s: &[SoakSample]| median(s.iter().map(|s| s.median_ms).collect());
    let time_drift = if earlier.is_empty() { 0.0 } else { ms(later) / ms(earlier) - 1.0 };
    SoakReport { samples, warm, rss_growth, rss_range, fd_growth, time_ratio, time_drift }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn loops_forwards_and_back() {
        let seq: Vec<usize> = (0..9).map(|i| ping_pong(i, 4)).collect();
        assert_eq!(seq, [0, 1, 2, 3, 2, 1, 0, 1, 2]);
        assert_eq!(ping_pong(5, 1), 0);
    }

    #[test]
    fn growth_is_measured_after_warm_up() {
        let s = |frame, rss_mb, fds| SoakSample { frame, rss_mb, rss_held_mb: rss_mb, fds, median_ms: 10.0 };
        let mut v = vec![s(1, 50.0, 5)];
        // A swing of a few MB either way after warm-up is not growth.
        v.extend((2..12).map(|i| s(i, if i % 3 == 0 { 103.0 } else { 100.0 + i as f64 * 0.01 }, 5)));
        let r = summarise(v.clone(), 1);
        assert_eq!(r.warm, 1);
        let limits = SoakLimits { rss: 0.02, time: 0.25 };
        assert!(r.rss_growth.abs() < 0.01 && r.holds(limits) && r.rss_range == (100.02, 103.0), "{r:?}");
        assert_eq!(r.time_drift, 0.0);
        let mut slower = v.clone();
        slower.iter_mut().skip(7).for_each(|s| s.median_ms = 14.0);
        let r = summarise(slower, 1);
        assert!((r.time_drift - 0.4).abs() < 1e-9 && !r.holds(limits), "{r:?}");
        // One slow window is a swing, not a drift.
        let mut swing = v.clone();
        swing[9].median_ms = 30.0;
        assert!(summarise(swing, 1).holds(limits));
        v.push(s(12, 110.0, 6));
        let r = summarise(v, 1);
        assert!(!r.holds(limits) && r.fd_growth == 1);
    }
}

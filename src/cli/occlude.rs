//! `prl occlude`: make a lost-and-found sequence from a real one (the target covered for a span
//! of frames while the view pans), for measuring lost-target signals and re-detection.

use std::path::PathBuf;

use clap::Args;
use prl_track::occlusion::LostAndFound;

#[derive(Args)]
pub struct OccludeArgs {
    /// OTB/UAV123-style sequence folder with ground truth.
    #[arg(long, value_name = "DIR", default_value = "../shared/data/uav123_10fps/building4")]
    sequence: PathBuf,
    /// Output folder (img/*.png, groundtruth_rect.txt with NaN rows where the target is hidden).
    #[arg(long, value_name = "DIR")]
    out: PathBuf,
    /// First hidden frame (0-based).
    #[arg(long, value_name = "N", default_value_t = 20)]
    hide_from: usize,
    /// How many frames the target stays hidden.
    #[arg(long, value_name = "N", default_value_t = 20)]
    hide_frames: usize,
    /// How far the view moves while the target is hidden, in pixels: DX,DY.
    #[arg(long, value_name = "DX,DY", default_value = "240,0", value_parser = parse_pan)]
    pan: (i64, i64),
    /// The view's size in pixels: WxH.
    #[arg(long, value_name = "WxH", default_value = "960x540", value_parser = parse_size)]
    view: (usize, usize),
}

fn parse_pan(s: &str) -> Result<(i64, i64), String> {
    let (a, b) = s.split_once(',').ok_or("expected DX,DY")?;
    Ok((
        a.trim().parse().map_err(|_| format!("`{a}` is not an integer"))?,
        b.trim().parse().map_err(|_| format!("`{b}` is not an integer"))?,
    ))
}

fn parse_size(s: &str) -> Result<(usize, usize), String> {
    let (a, b) = s.split_once('x').ok_or("expected WxH")?;
    Ok((
        a.trim().parse().map_err(|_| format!("`{a}` is not a size"))?,
        b.trim().parse().map_err(|_| format!("`{b}` is not a size"))?,
    ))
}

pub fn run(a: OccludeArgs) -> anyhow::Result<()> {
    let spec = LostAndFound { hide_from: a.hide_from, hide_frames: a.hide_frames, pan: a.pan, view: a.view };
    let n = spec.make(&a.sequence, &a.out)?;
    println!(
        "{}: {n} frames of {}x{} from {}, target hidden on frames {}..{} while the view pans by {},{}",
        a.out.display(),
        a.view.0,
        a.view.1,
        a.sequence.display(),
        a.hide_from,
        a.hide_from + a.hide_frames,
        a.pan.0,
        a.pan.1
    );
    Ok(())
}

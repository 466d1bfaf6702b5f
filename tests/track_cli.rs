//! `prl track` and `prl compile` as a user runs them: results files, frame conversions, errors.

mod common;

use common::prl;

use std::path::Path;
use std::process::Output;

fn stderr(o: &Output) -> String {
    String::from_utf8_lossy(&o.stderr).trim().to_string()
}

fn drift_frame(i: usize) -> image::RgbImage {
    image::open(common::golden_dir().join(format!("seq_drift/img/{i:06}.png"))).unwrap().to_rgb8()
}

/// Three frames; the second as 16-bit grey, which is converted to 8-bit colour.
fn frames_dir(dir: &Path) {
    drift_frame(1).save(dir.join("000001.png")).unwrap();
    let grey = image::DynamicImage::ImageRgb8(drift_frame(2)).to_luma16();
    grey.save(dir.join("000002.png")).unwrap();
    drift_frame(3).save(dir.join("000003.png")).unwrap();
}

#[test]
fn track_a_frame_folder_and_write_results() {
    let plan = common::reference_plan();
    let dir = tempfile::tempdir().unwrap();
    frames_dir(dir.path());
    let results = dir.path().join("out/results.txt");
    std::fs::create_dir(dir.path().join("out")).unwrap();
    let vis = dir.path().join("vis");
    let o = prl(&[
        "track",
        "--plan",
        plan.to_str().unwrap(),
        "--frames",
        dir.path().to_str().unwrap(),
        "--init",
        "110.5,108.5,36,24",
        "--results",
        results.to_str().unwrap(),
        "--vis",
        vis.to_str().unwrap(),
        "--threads",
        "1",
    ]);
    assert!(o.status.success(), "{}", stderr(&o));
    let lines: Vec<String> = std::fs::read_to_string(&results).unwrap().lines().map(str::to_string).collect();
    assert_eq!(lines.len(), 3);
    assert_eq!(lines[0], "110.5,108.5,36,24");
    let stdout = String::from_utf8_lossy(&o.stdout);
    assert!(stdout.contains("frames: 3") && stdout.contains("network"), "{stdout}");
    assert_eq!(std::fs::read_dir(&vis).unwrap().count(), 3);
    // --jsonl on a frame folder: standard output is one object a frame, nothing else.
    let o = prl(&[
        "track",
        "--plan",
        plan.to_str().unwrap(),
        "--frames",
        dir.path().to_str().unwrap(),
        "--init",
        "110.5,108.5,36,24",
        "--jsonl",
        "--threads",
        "1",
    ]);
    assert!(o.status.success(), "{}", stderr(&o));
    let objs: Vec<serde_json::Value> =
        String::from_utf8_lossy(&o.stdout).lines().map(|l| serde_json::from_str(l).unwrap()).collect();
    assert_eq!(objs.len(), 3);
    assert_eq!((objs[0]["frame"].as_u64(), objs[2]["frame"].as_u64()), (Some(0), Some(2)));
    assert_eq!(objs[0]["state"], "tracking");
    for o in &objs {
        assert!(["tracking", "uncertain", "lost"].contains(&o["state"].as_str().unwrap()), "{o}");
        assert!(o["confidence"].as_f64().is_some() && o["box"].as_array().unwrap().len() == 4, "{o}");
    }
    assert!(stderr(&o).contains("frames: 3"), "the summary goes to standard error with --jsonl");
}

#[test]
fn several_targets_and_the_long_term_mode_from_the_command_line() {
    let plan = common::reference_plan();
    let dir = tempfile::tempdir().unwrap();
    frames_dir(dir.path());
    let results = dir.path().join("results.txt");
    let run = |extra: &[&str]| {
        let mut args = vec!["track", "--plan", plan.to_str().unwrap(), "--frames", dir.path().to_str().unwrap()];
        args.extend_from_slice(&["--results", results.to_str().unwrap(), "--threads", "2"]);
        args.extend_from_slice(extra);
        prl(&args)
    };
    // One target: its results, and its confidences beside them.
    assert!(run(&["--init", "110.5,108.5,36,24", "--long-term"]).status.success());
    let single = std::fs::read_to_string(&results).unwrap();
    let conf = std::fs::read_to_string(dir.path().join("results_confidence.value")).unwrap();
    assert_eq!((single.lines().count(), conf.lines().count()), (3, 3));
    // Two targets: one file each, the first as the single run; JSON lines carry the target.
    let o = run(&["--init", "110.5,108.5,36,24", "--init", "20,30,40,40", "--long-term", "--jsonl"]);
    assert!(o.status.success(), "{}", stderr(&o));
    assert_eq!(std::fs::read_to_string(dir.path().join("results_1.txt")).unwrap(), single);
    let second = std::fs::read_to_string(dir.path().join("results_2.txt")).unwrap();
    assert_eq!(second.lines().next(), Some("20,30,40,40"));
    let objs: Vec<serde_json::Value> =
        String::from_utf8_lossy(&o.stdout).lines().map(|l| serde_json::from_str(l).unwrap()).collect();
    let targets: Vec<u64> = objs.iter().map(|o| o["target"].as_u64().unwrap()).collect();
    assert_eq!(targets, [1, 2, 1, 2, 1, 2]);
    assert!(stderr(&o).contains("targets: 2 on 2 thread(s)"), "{}", stderr(&o));
    // A refused second box is quoted as typed, with its target.
    let o = run(&["--init", "110.5,108.5,36,24", "--init", "9e9,0,5,5"]);
    let e = stderr(&o);
    assert!(!o.status.success() && e.contains("--init 9e9,0,5,5") && e.contains("(target 2)"), "{e}");
    // The same targets from a file: the same results.
    let first = std::fs::read_to_string(dir.path().join("results_1.txt")).unwrap();
    let file = dir.path().join("targets.txt");
    std::fs::write(&file, "110.5,108.5,36,24\n\n20 30 40 40\n").unwrap();
    let o = run(&["--targets", file.to_str().unwrap(), "--long-term"]);
    assert!(o.status.success(), "{}", stderr(&o));
    assert_eq!(std::fs::read_to_string(dir.path().join("results_1.txt")).unwrap(), first);
    assert_eq!(std::fs::read_to_string(dir.path().join("results_2.txt")).unwrap(), second);
    // A bad line is named; a refused box is quoted from its line.
    std::fs::write(&file, "110.5,108.5,36,24\n20,30,40\n").unwrap();
    let e = stderr(&run(&["--targets", file.to_str().unwrap()]));
    assert!(e.contains("targets.txt: line 2: expected 4 numbers"), "{e}");
    std::fs::write(&file, "110.5,108.5,36,24\n9e9,0,5,5\n").unwrap();
    let e = stderr(&run(&["--targets", file.to_str().unwrap()]));
    assert!(e.contains("targets.txt line 2 (9e9,0,5,5)") && e.contains("outside"), "{e}");
    // A sequence folder with one ground-truth file per target (OTB's Jogging): both tracked,
    // each from its file's first box as tools/test.py hands it to init (x + 0.5, y + 0.5).
    let seq = dir.path().join("Jogging");
    frames_dir(&{
        std::fs::create_dir_all(seq.join("img")).unwrap();
        seq.join("img")
    });
    std::fs::write(seq.join("groundtruth_rect.1.txt"), "110,108,36,24\n110,108,36,24\n110,108,36,24\n").unwrap();
    std::fs::write(seq.join("groundtruth_rect.2.txt"), "19.5,29.5,40,40\n19.5,29.5,40,40\nNaN,NaN,NaN,NaN\n").unwrap();
    let seq_results = dir.path().join("jogging.txt");
    let o = prl(&[
        "track",
        "--plan",
        plan.to_str().unwrap(),
        "--sequence",
        seq.to_str().unwrap(),
        "--results",
        seq_results.to_str().unwrap(),
        "--threads",
        "2",
        "--long-term",
    ]);
    let out = String::from_utf8_lossy(&o.stdout);
    assert!(o.status.success(), "{}", stderr(&o));
    assert_eq!(std::fs::read_to_string(dir.path().join("jogging_1.txt")).unwrap(), first);
    assert_eq!(std::fs::read_to_string(dir.path().join("jogging_2.txt")).unwrap(), second);
    assert!(
        out.contains("targets: 2 on 2 thread(s)")
            && out.contains("mean IoU per target: 1: 0.")
            && out.contains(", 2: "),
        "{out}"
    );
    // A refused box is quoted from its ground-truth file.
    std::fs::write(seq.join("groundtruth_rect.2.txt"), "9e9,0,5,5\n1,1,5,5\n1,1,5,5\n").unwrap();
    let e = stderr(&prl(&["track", "--plan", plan.to_str().unwrap(), "--sequence", seq.to_str().unwrap()]));
    assert!(e.contains("groundtruth_rect.2.txt line 1 (9e9,0,5,5)") && e.contains("outside"), "{e}");
}

#[test]
fn eval_reports_long_term_figures_where_the_target_is_absent() {
    // A three-frame video whose target is absent on frame 2, and a tracker's results with their
    // confidences: VOT-LT's figures as pysot-toolkit computes them.
    let root = tempfile::tempdir().unwrap();
    let video = root.path().join("data/vid");
    std::fs::create_dir_all(video.join("img")).unwrap();
    frames_dir(&video.join("img"));
    std::fs::write(video.join("groundtruth_rect.txt"), "10,10,20,20\nNaN,NaN,NaN,NaN\n30,30,20,20\n").unwrap();
    let res = root.path().join("results/tracker");
    std::fs::create_dir_all(&res).unwrap();
    std::fs::write(res.join("vid.txt"), "10,10,20,20\n60,60,20,20\n30,30,20,10\n").unwrap();
    std::fs::write(res.join("vid_confidence.value"), "1\n0.3\n0.9\n").unwrap();
    let data = root.path().join("data");
    let out = common::ok(&prl(&[
        "eval",
        "--dataset",
        data.to_str().unwrap(),
        "--results",
        res.parent().unwrap().to_str().unwrap(),
    ]));
    // Frame 3 (confidence 0.9, overlap 0.5) alone: precision 0.5, recall 0.5 / 2 present frames.
    let row = out.lines().skip_while(|l| !l.starts_with("long-term")).find(|l| l.contains("tracker")).unwrap();
    let cells: Vec<&str> = row.split('|').map(str::trim).collect();
    assert_eq!(&cells[2..5], ["0.500", "0.250", "0.333"], "{out}");
    // Without the confidences file: a note, no figures.
    std::fs::remove_file(res.join("vid_confidence.value")).unwrap();
    let out = common::ok(&prl(&[
        "eval",
        "--dataset",
        data.to_str().unwrap(),
        "--results",
        res.parent().unwrap().to_str().unwrap(),
    ]));
    assert!(out.contains("results without confidences"), "{out}");
}

#[test]
fn bad_track_inputs_are_one_line_errors() {
    let plan = common::reference_plan();
    let plan = plan.to_str().unwrap();
    let dir = tempfile::tempdir().unwrap();
    frames_dir(dir.path());
    let d = dir.path().to_str().unwrap();
    let check = |args: &[&str], needle: &str| {
        let o = prl(args);
        assert!(!o.status.success(), "{args:?} succeeded");
        let err = stderr(&o);
        assert!(err.lines().count() == 1 && err.starts_with("error: ") && err.contains(needle), "{args:?}: {err}");
    };
    check(&["track", "--plan", plan, "--frames", d, "--init", "400,300,10,10"], "outside");
    check(&["track", "--plan", plan, "--frames", d, "--init", "10,10,0,5"], "must be positive");
    check(&["track", "--plan", plan, "--frames", d, "--init", "10,10,nan,5"], "must be finite");
    // A box far larger than the frame: refused before any crop is allocated, quoted as typed.
    check(&["track", "--plan", plan, "--frames", d, "--init", "0,0,1e7,1e7"], "--init 0,0,1e7,1e7: is larger than the");
    check(&["track", "--plan", plan, "--frames", d, "--init", "-5e299,0,1e300,20"], "--init -5e299,0,1e300,20");
    // From a sequence's ground truth: the file's line, as written.
    let seq = tempfile::tempdir().unwrap();
    std::fs::create_dir(seq.path().join("img")).unwrap();
    frames_dir(&seq.path().join("img"));
    std::fs::write(seq.path().join("groundtruth_rect.txt"), "\n0,0,2e4,1e1\n1,1,1,1\n1,1,1,1\n").unwrap();
    let s = seq.path().to_str().unwrap();
    check(&["track", "--plan", plan, "--sequence", s], "groundtruth_rect.txt line 2 (0,0,2e4,1e1): is larger than");
    check(&["track", "--plan", plan, "--frames", d, "--init", "10,10,0.1,0.1"], "too small");
    // Malformed arguments are clap's usage errors (exit 2, with its hint line).
    let o = prl(&["track", "--plan", plan, "--frames", d, "--init", "10,10,5"]);
    assert_eq!(o.status.code(), Some(2));
    assert!(stderr(&o).contains("expected 4 numbers x,y,w,h"), "{}", stderr(&o));
    check(
        &["track", "--plan", plan, "--frames", d, "--init", "110,108,36,24", "--results", "/nonexistent/dir/r.txt"],
        "/nonexistent/dir/r.txt",
    );
    check(&["track", "--plan", "/nonexistent/plan", "--frames", d, "--init", "110,108,36,24"], "/nonexistent/plan");
    // A frame of another size, and a broken JPEG: named.
    image::RgbImage::new(64, 48).save(dir.path().join("000004.png")).unwrap();
    check(&["track", "--plan", plan, "--frames", d, "--init", "110,108,36,24"], "000004.png");
    std::fs::remove_file(dir.path().join("000004.png")).unwrap();
    std::fs::write(dir.path().join("000004.jpg"), b"\xff\xd8\xff\xe0 not really a jpeg").unwrap();
    check(&["track", "--plan", plan, "--frames", d, "--init", "110,108,36,24"], "000004.jpg");
}

/// A JPEG cut short decodes (the lost part grey, as OpenCV gives it) with a warning naming it;
/// `--strict` makes it an error.
#[test]
fn damaged_jpeg_frames_warn_or_fail_with_strict() {
    let plan = common::reference_plan();
    let dir = tempfile::tempdir().unwrap();
    for i in 1..=3 {
        drift_frame(i).save(dir.path().join(format!("{i:06}.jpg"))).unwrap();
    }
    let cut = dir.path().join("000002.jpg");
    let bytes = std::fs::read(&cut).unwrap();
    std::fs::write(&cut, &bytes[..bytes.len() / 3]).unwrap();
    let (frame, damage) = prl_track::decode_frame(&cut).unwrap();
    assert!(damage.as_deref().is_some_and(|d| d.contains("Premature end")), "{damage:?}");
    assert!(frame.bgr().iter().any(|&b| b != 128), "a grey frame");
    let whole = dir.path().join("000001.jpg");
    assert_eq!(prl_track::decode_frame(&whole).unwrap().1, None);
    // The header alone gives the size, of a cut frame too; a declared size over the limit is
    // refused from the header (the SOF0 marker's height and width set to 9000).
    let img = drift_frame(1);
    let size = (img.width() as usize, img.height() as usize);
    assert_eq!(prl_track::frame_size(&cut, &bytes[..bytes.len() / 3]).unwrap(), size);
    let mut huge = std::fs::read(&whole).unwrap();
    let sof = huge.windows(2).position(|m| m == [0xff, 0xc0]).expect("a baseline JPEG");
    huge[sof + 5..sof + 9].copy_from_slice(&[0x23, 0x28, 0x23, 0x28]);
    let err = prl_track::frame_size(&whole, &huge).unwrap_err().to_string();
    assert!(err.contains("000001.jpg") && err.contains("declares 9000x9000 pixels"), "{err}");

    let args = |strict: bool| {
        let mut a = vec!["track", "--plan", plan.to_str().unwrap(), "--frames", dir.path().to_str().unwrap()];
        a.extend(["--init", "110.5,108.5,36,24", "--threads", "1"]);
        if strict {
            a.push("--strict");
        }
        a.into_iter().map(str::to_string).collect::<Vec<_>>()
    };
    let run = |strict| prl(&args(strict).iter().map(String::as_str).collect::<Vec<_>>());
    let o = run(false);
    assert!(o.status.success(), "{}", stderr(&o));
    let warnings: Vec<&str> =
        std::str::from_utf8(&o.stderr).unwrap().lines().filter(|l| l.starts_with("warning")).collect();
    assert_eq!(warnings.len(), 1, "{warnings:?}");
    assert!(warnings[0].contains("000002.jpg") && warnings[0].contains("damaged frame"), "{}", warnings[0]);
    assert!(String::from_utf8_lossy(&o.stdout).contains("frames: 3"));
    let o = run(true);
    assert!(!o.status.success());
    let err = stderr(&o);
    assert!(err.lines().count() == 1 && err.contains("000002.jpg: damaged frame: Premature end"), "{err}");
}

#[test]
fn bench_reports_stages_and_operators() {
    let plan = common::reference_plan();
    let dir = tempfile::tempdir().unwrap();
    let json = dir.path().join("bench.json");
    let seq = common::golden_dir().join("seq_drift");
    let o = prl(&[
        "bench",
        "--plan",
        plan.to_str().unwrap(),
        "--runs",
        "2",
        "--template-runs",
        "1",
        "--sequence",
        seq.to_str().unwrap(),
        "--json",
        json.to_str().unwrap(),
        "--save-tensors",
        dir.path().join("tensors").to_str().unwrap(),
    ]);
    assert!(o.status.success(), "{}", stderr(&o));
    let out = String::from_utf8_lossy(&o.stdout);
    assert!(out.contains("peak resident memory"), "{out}");
    // The networks' inputs and outputs, for other runtimes: raw f32 of the shapes listed.
    let index: serde_json::Value =
        serde_json::from_slice(&std::fs::read(dir.path().join("tensors/tensors.json")).unwrap()).unwrap();
    let names: Vec<&String> = index.as_object().unwrap().keys().collect();
    assert_eq!(names.len(), 10, "z, x, zf1..zf5, loc, cls1, cls2: {names:?}");
    for (name, shape) in index.as_object().unwrap() {
        let n: u64 = shape.as_array().unwrap().iter().map(|d| d.as_u64().unwrap()).product();
        let len = std::fs::metadata(dir.path().join(format!("tensors/{name}.f32"))).unwrap().len();
        assert_eq!(len, 4 * n, "{name}");
    }
    let report: serde_json::Value = serde_json::from_slice(&std::fs::read(&json).unwrap()).unwrap();
    let stages: Vec<&str> = report["stages"].as_array().unwrap().iter().map(|s| s["stage"].as_str().unwrap()).collect();
    assert_eq!(stages, ["template network", "crop + resize", "search network", "post-processing", "tracking step"]);
    // Two timed tracking steps, one timed template run (`--template-runs`).
    let samples: Vec<usize> =
        report["stages"].as_array().unwrap().iter().map(|s| s["samples_ms"].as_array().unwrap().len()).collect();
    assert_eq!(samples, [1, 2, 2, 2, 2]);
    let ops = report["top_ops"].as_array().unwrap();
    assert_eq!(ops.len(), 12);
    assert!(ops.iter().any(|o| o["gflops"].as_f64().unwrap() > 0.0));
    // The template graph's profile too: its convolutions, with their rates.
    // (At most the 12 asked for: with the ReLUs fused into the convolutions, PRL-Track's
    // template graph has 11 operators.)
    let template = report["template_ops"].as_array().unwrap();
    assert!((8..=12).contains(&template.len()), "{template:?}");
    assert!(template.iter().any(|o| o["op"] == "PackedConv" && o["gflops"].as_f64().unwrap() > 0.0), "{template:?}");
    assert!(out.contains("slowest operators of the template graph"), "{out}");
}

/// A plan's Winograd choice (`plan.json`'s `winograd`) puts `WinogradConv` in both graphs where
/// it serves (PRL-Track's 5x5 layer 2 and 3x3 layers 3-5), `PRL_WINOGRAD` overrides it, and a
/// choice the runtime does not know is a one-line error naming the manifest.
#[test]
fn winograd_is_the_plan_s_choice_and_the_environment_overrides_it() {
    let reference = common::reference_plan();
    let dir = tempfile::tempdir().unwrap();
    let plan = dir.path().join("plan");
    std::fs::create_dir(&plan).unwrap();
    for f in std::fs::read_dir(&reference).unwrap() {
        let f = f.unwrap().path();
        std::fs::copy(&f, plan.join(f.file_name().unwrap())).unwrap();
    }
    let manifest = plan.join("plan.json");
    let mut m: serde_json::Value = serde_json::from_slice(&std::fs::read(&manifest).unwrap()).unwrap();
    m["winograd"] = "all".into();
    std::fs::write(&manifest, serde_json::to_vec(&m).unwrap()).unwrap();
    let json = dir.path().join("bench.json");
    let bench = |env: Option<&str>| {
        let mut cmd = std::process::Command::new(env!("CARGO_BIN_EXE_prl"));
        cmd.args(["bench", "--plan", plan.to_str().unwrap(), "--runs", "1", "--top", "60"]);
        cmd.args(["--json", json.to_str().unwrap()]);
        match env {
            Some(v) => cmd.env("PRL_WINOGRAD", v),
            None => cmd.env_remove("PRL_WINOGRAD"),
        };
        let o = cmd.output().unwrap();
        assert!(o.status.success(), "{}", stderr(&o));
        let report: serde_json::Value = serde_json::from_slice(&std::fs::read(&json).unwrap()).unwrap();
        // (name, kernel) of each WinogradConv.
        let kernels = |graph: &str| -> Vec<(String, String)> {
            let ops = report[graph].as_array().unwrap().iter().filter(|o| o["op"] == "WinogradConv");
            ops.map(|o| (o["name"].as_str().unwrap().to_string(), o["kernel"].as_str().unwrap().to_string())).collect()
        };
        (String::from_utf8_lossy(&o.stdout).into_owned(), kernels("top_ops"), kernels("template_ops"))
    };
    let (out, search, template) = bench(None);
    assert!(out.contains("convolutions as Winograd's: all (the plan's choice)"), "{out}");
    // The backbone's large layers always (which small ones pay depends on the kernel's tile).
    let has = |ops: &[(String, String)], name: &str, form: &str| ops.iter().any(|(n, k)| n == name && k.contains(form));
    assert!(has(&search, "backbone_layer2_conv_conv", "F(2x2,5x5)"), "{search:?}");
    for name in ["backbone_layer3_conv_conv", "backbone_layer4_conv_conv", "xf5_conv"] {
        assert!(has(&search, name, "F(2x2,3x3)"), "{name}: {search:?}");
    }
    assert!(has(&template, "backbone_layer2_conv_conv", "F(2x2,5x5)"), "{template:?}");
    let (out, search, template) = bench(Some("off"));
    assert!(out.contains("convolutions as Winograd's: off (PRL_WINOGRAD)"), "{out}");
    assert!(search.is_empty() && template.is_empty(), "{search:?} {template:?}");
    m["winograd"] = "5x5".into();
    std::fs::write(&manifest, serde_json::to_vec(&m).unwrap()).unwrap();
    let o = prl(&["bench", "--plan", plan.to_str().unwrap(), "--runs", "1"]);
    let err = stderr(&o);
    assert!(!o.status.success() && err.lines().count() == 1, "{err}");
    assert!(err.contains("plan.json") && err.contains("5x5"), "{err}");
}

/// `list_frames` takes jpg, png, bmp and webp: each lossless format decodes to the same pixels.
#[test]
fn png_bmp_and_webp_frames_decode_alike() {
    let dir = tempfile::tempdir().unwrap();
    let img = drift_frame(1);
    let mut frames = vec![];
    for ext in ["png", "bmp", "webp"] {
        let p = dir.path().join(format!("f.{ext}"));
        img.save(&p).unwrap();
        let (frame, damage) = prl_track::decode_frame(&p).unwrap();
        assert!(damage.is_none());
        let size = prl_track::frame_size(&p, &std::fs::read(&p).unwrap()).unwrap();
        assert_eq!(size, (frame.width(), frame.height()), "{ext}");
        frames.push(frame);
    }
    assert!(frames.iter().all(|f| *f == frames[0]), "the same pixels from every format");
    assert_eq!((frames[0].width(), frames[0].height()), (img.width() as usize, img.height() as usize));
}

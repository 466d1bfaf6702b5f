//! Every dataset layout, from small trees made here (frames are empty files: reading a dataset
//! never decodes an image), and the errors on malformed ones.

use std::path::Path;

use prl_track::{detect, Dataset, Format};

fn touch(p: &Path, text: &str) {
    std::fs::create_dir_all(p.parent().unwrap()).unwrap();
    std::fs::write(p, text).unwrap();
}

fn frames(dir: &Path, n: usize) {
    for i in 1..=n {
        touch(&dir.join(format!("{i:06}.jpg")), "");
    }
}

const GT3: &str = "1,2,3,4\n5\t6\t7\t8\nNaN,NaN,NaN,NaN\n";

#[test]
fn otb_and_got10k_folders() {
    let t = tempfile::tempdir().unwrap();
    let otb = t.path().join("DTB70");
    frames(&otb.join("b/img"), 3);
    touch(&otb.join("b/groundtruth_rect.txt"), GT3);
    frames(&otb.join("a/img"), 3);
    touch(&otb.join("a/groundtruth_rect.txt"), "1 2 3 4\n1.5 2.5 3.5 4.5\n0,0,0,0\n");
    assert_eq!(detect(&otb).unwrap(), Format::Otb);
    let d = Dataset::open(&otb, Format::Auto).unwrap();
    assert_eq!(d.name, "DTB70");
    assert_eq!(d.videos.iter().map(|v| v.name.as_str()).collect::<Vec<_>>(), ["a", "b"]);
    let b = &d.videos[1];
    assert_eq!(b.frames.len(), 3);
    assert_eq!(b.groundtruth[1], [5.0, 6.0, 7.0, 8.0]);
    assert!(b.groundtruth[2].iter().all(|v| v.is_nan()), "NaN rows kept");
    assert_eq!(b.init, [1.0, 2.0, 3.0, 4.0]);
    // A sequence with one ground-truth file per target is one video per target, named as
    // pysot-toolkit's OTB names them; a lone numbered file keeps the sequence's name.
    frames(&otb.join("Jogging/img"), 3);
    touch(&otb.join("Jogging/groundtruth_rect.1.txt"), GT3);
    touch(&otb.join("Jogging/groundtruth_rect.2.txt"), "9,9,9,9\n9,9,9,9\n9,9,9,9\n");
    frames(&otb.join("Human4/img"), 3);
    touch(&otb.join("Human4/groundtruth_rect.2.txt"), GT3);
    let d = Dataset::open(&otb, Format::Auto).unwrap();
    let names: Vec<_> = d.videos.iter().map(|v| v.name.as_str()).collect();
    assert_eq!(names, ["Human4", "Jogging-1", "Jogging-2", "a", "b"]);
    assert_eq!((d.videos[1].init, d.videos[2].init), ([1.0, 2.0, 3.0, 4.0], [9.0; 4]));
    assert_eq!(d.videos[2].frames, d.videos[1].frames);
    for v in ["Human4", "Jogging"] {
        std::fs::remove_dir_all(otb.join(v)).unwrap();
    }

    let got = t.path().join("GOT-10k_val");
    frames(&got.join("GOT-10k_Val_000001"), 3);
    touch(&got.join("GOT-10k_Val_000001/groundtruth.txt"), GT3);
    assert_eq!(detect(&got).unwrap(), Format::Got10k);
    assert_eq!(Dataset::open(&got, Format::Auto).unwrap().videos[0].frames.len(), 3);
}

#[test]
fn uav123_raw_with_attributes_and_sub_sequence_error() {
    let t = tempfile::tempdir().unwrap();
    let root = t.path().join("Dataset_UAV123");
    frames(&root.join("data_seq/UAV123/bike1"), 3);
    touch(&root.join("anno/UAV123/bike1.txt"), GT3);
    touch(&root.join("anno/UAV123/att/bike1.txt"), "1,1,0,0,0,1,0,0,0,0,0,0\n");
    assert_eq!(detect(&root).unwrap(), Format::Uav123);
    let d = Dataset::open(&root, Format::Auto).unwrap();
    assert_eq!(d.name, "UAV123");
    assert_eq!(d.videos[0].attributes, ["Scale Variation", "Aspect Ratio Change", "Partial Occlusion"]);
    assert_eq!(d.attributes()["Partial Occlusion"], ["bike1"]);
    // bird1_1 has no frame folder of its own: only the JSON knows its range.
    touch(&root.join("anno/UAV123/bird1_1.txt"), GT3);
    let e = Dataset::open(&root, Format::Auto).unwrap_err().to_string();
    assert!(e.contains("bird1_1.txt") && e.contains("pysot-json"), "{e}");
}

#[test]
fn uav112_and_uav112l() {
    let t = tempfile::tempdir().unwrap();
    let root = t.path().join("UAVTrack112");
    frames(&root.join("data_seq/air conditioning box1"), 3);
    frames(&root.join("data_seq/car1"), 3);
    touch(&root.join("anno/air conditioning box1.txt"), GT3);
    touch(&root.join("anno/car1.txt"), GT3);
    assert_eq!(detect(&root).unwrap(), Format::Uav112);
    assert_eq!(Dataset::open(&root, Format::Auto).unwrap().videos.len(), 2);
    touch(&root.join("anno_l/car1.txt"), GT3);
    let l = Dataset::open(&root, Format::Uav112l).unwrap();
    assert_eq!(l.name, "UAVTrack112_L");
    assert_eq!(l.videos.len(), 1);
}

#[test]
fn pysot_json_with_sub_sequences_and_nan() {
    let t = tempfile::tempdir().unwrap();
    let root = t.path().join("UAV123");
    touch(
        &root.join("UAV123.json"),
        r#"{"bird1_1": {"video_dir": "bird1", "init_rect": [1, 2, 3, 4],
            "img_names": ["bird1/000001.jpg", "bird1/000002.jpg"],
            "gt_rect": [[1, 2, 3, 4], [NaN, NaN, NaN, NaN]], "attr": ["Full Occlusion"]}}"#,
    );
    assert_eq!(detect(&root).unwrap(), Format::PysotJson);
    let d = Dataset::open(&root, Format::Auto).unwrap();
    assert_eq!(d.name, "UAV123");
    let v = &d.videos[0];
    assert_eq!(v.name, "bird1_1");
    assert_eq!(v.frames[1], root.join("bird1/000002.jpg"));
    assert!(v.groundtruth[1][0].is_nan());
    assert_eq!(v.attributes, ["Full Occlusion"]);
}

#[test]
fn malformed_inputs_are_clear_errors() {
    let t = tempfile::tempdir().unwrap();
    let root = t.path().join("OTB");
    frames(&root.join("a/img"), 2);
    touch(&root.join("a/groundtruth_rect.txt"), "1,2,3,4\n1,2,x,4\n");
    let e = Dataset::open(&root, Format::Auto).unwrap_err().to_string();
    assert!(e.contains("groundtruth_rect.txt") && e.contains("line 2"), "{e}");
    let empty = t.path().join("empty");
    std::fs::create_dir_all(&empty).unwrap();
    assert!(Dataset::open(&empty, Format::Auto).unwrap_err().to_string().contains("unknown dataset layout"));
    let json = t.path().join("J");
    touch(&json.join("x.json"), "[1, 2]");
    assert!(Dataset::open(&json, Format::Auto).unwrap_err().to_string().contains("x.json"));
    assert!(Dataset::open(&t.path().join("missing"), Format::Auto).unwrap_err().to_string().contains("not a folder"));
}

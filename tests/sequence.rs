//! Sequence folders and box files, as OTB / UAV123 lay them out.

use prl_track::{box_file_limit, init_box_from_groundtruth, parse_box, parse_boxes, Sequence};

#[test]
fn boxes_with_any_separator_and_nan_rows() {
    let dir = tempfile::tempdir().unwrap();
    let p = dir.path().join("gt.txt");
    std::fs::write(&p, "1,2,3,4\n5\t6\t7\t8\n9 10  11 12\n\nNaN,NaN,NaN,NaN\n1.5,2.25,3,4\n").unwrap();
    let b = parse_boxes(&p, 6).unwrap();
    assert_eq!(b.len(), 5);
    assert_eq!(b[1], [5., 6., 7., 8.]);
    assert_eq!(b[2], [9., 10., 11., 12.]);
    assert!(b[3].iter().all(|v| v.is_nan()));
    assert_eq!(b[4], [1.5, 2.25, 3., 4.]);
    std::fs::write(&p, "1,2,3,4\n1,2,x,4\n").unwrap();
    let err = parse_boxes(&p, 6).unwrap_err().to_string();
    assert!(err.contains("gt.txt") && err.contains("line 2") && err.contains("`x`"), "{err}");
    assert!(parse_box("1,2,3").is_err());
    // Longer than any box file of 6 frames: refused before it is read (a sparse 1 MiB + 7 KiB).
    std::fs::File::create(&p).unwrap().set_len(box_file_limit(6) + 1).unwrap();
    let err = parse_boxes(&p, 6).unwrap_err().to_string();
    assert!(err.contains("gt.txt") && err.contains("too long for a box file of 6 frames"), "{err}");
}

#[test]
fn init_box_is_what_tools_test_py_hands_to_init() {
    let b = init_box_from_groundtruth([110., 108., 36., 24.]);
    assert_eq!([b.x, b.y, b.w, b.h], [110.5, 108.5, 36., 24.]);
}

#[test]
fn sequence_folders() {
    let dir = tempfile::tempdir().unwrap();
    std::fs::create_dir(dir.path().join("img")).unwrap();
    for i in [2, 1, 3] {
        std::fs::write(dir.path().join(format!("img/{i:06}.jpg")), b"").unwrap();
    }
    std::fs::write(dir.path().join("img/notes.txt"), b"").unwrap();
    std::fs::write(dir.path().join("groundtruth_rect.txt"), "1,1,5,5\n2,2,5,5\n3,3,5,5\n").unwrap();
    let s = Sequence::open(dir.path()).unwrap();
    let names: Vec<_> = s.frames.iter().map(|p| p.file_name().unwrap().to_string_lossy().into_owned()).collect();
    assert_eq!(names, ["000001.jpg", "000002.jpg", "000003.jpg"]);
    assert_eq!(s.groundtruth().unwrap().len(), 3);
    std::fs::write(dir.path().join("groundtruth_rect.txt"), "1,1,5,5\n").unwrap();
    let err = Sequence::open(dir.path()).unwrap_err().to_string();
    assert!(err.contains("1 boxes for 3 frames"), "{err}");
    let empty = tempfile::tempdir().unwrap();
    assert!(Sequence::open(empty.path()).unwrap_err().to_string().contains("no frames"));
}

#[test]
fn several_targets_one_groundtruth_file_each() {
    let dir = tempfile::tempdir().unwrap();
    std::fs::create_dir(dir.path().join("img")).unwrap();
    for i in 1..=2 {
        std::fs::write(dir.path().join(format!("img/{i:06}.jpg")), b"").unwrap();
    }
    // OTB's numbering, taken in the order of the numbers (10 after 2), not of the names.
    for n in [10, 2, 1] {
        std::fs::write(dir.path().join(format!("groundtruth_rect.{n}.txt")), format!("{n},1,5,5\n{n},2,5,5\n"))
            .unwrap();
    }
    std::fs::write(dir.path().join("groundtruth_rect.x.txt"), "not a target's file").unwrap();
    let s = Sequence::open(dir.path()).unwrap();
    let numbers: Vec<_> = s.targets.iter().map(|t| t.number).collect();
    assert_eq!(numbers, [Some(1), Some(2), Some(10)]);
    assert_eq!(s.targets[2].boxes[1], [10.0, 2.0, 5.0, 5.0]);
    assert!(s.targets[2].file.ends_with("groundtruth_rect.10.txt"));
    assert_eq!(s.groundtruth(), Some(&s.targets[0].boxes));
    // One target's file too short is named.
    std::fs::write(dir.path().join("groundtruth_rect.2.txt"), "1,1,5,5\n").unwrap();
    let err = Sequence::open(dir.path()).unwrap_err().to_string();
    assert!(err.contains("groundtruth_rect.2.txt: 1 boxes for 2 frames"), "{err}");
    // Two files of one target are refused.
    std::fs::write(dir.path().join("groundtruth_rect.2.txt"), "1,1,5,5\n1,1,5,5\n").unwrap();
    std::fs::write(dir.path().join("groundtruth_rect.02.txt"), "1,1,5,5\n1,1,5,5\n").unwrap();
    let err = Sequence::open(dir.path()).unwrap_err().to_string();
    assert!(err.contains("a second ground-truth file of target 2"), "{err}");
    // A plain groundtruth_rect.txt is the one target.
    std::fs::write(dir.path().join("groundtruth_rect.txt"), "7,1,5,5\n7,2,5,5\n").unwrap();
    let s = Sequence::open(dir.path()).unwrap();
    assert_eq!((s.targets.len(), s.targets[0].number, s.targets[0].boxes[0][0]), (1, None, 7.0));
    // At most MAX_GROUNDTRUTH_FILES files, checked before they are read.
    std::fs::remove_file(dir.path().join("groundtruth_rect.txt")).unwrap();
    std::fs::remove_file(dir.path().join("groundtruth_rect.02.txt")).unwrap();
    for n in 11..=(prl_track::MAX_GROUNDTRUTH_FILES + 8) {
        std::fs::write(dir.path().join(format!("groundtruth_rect.{n}.txt")), "").unwrap();
    }
    let err = Sequence::open(dir.path()).unwrap_err().to_string();
    assert!(err.contains("more than 64 groundtruth_rect.<N>.txt files"), "{err}");
}

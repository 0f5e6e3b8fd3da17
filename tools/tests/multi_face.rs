//! `holoface multi-face` end to end: several validation faces in one rendered scene, tracked at once with
//! KRFWS, against the same faces tracked alone; and `holoface track --max-faces` on such a scene's frames.

mod common;

use common::{holoface, tmp};

#[test]
fn three_faces_keep_three_ids_and_their_accuracy() {
    let d = tmp("multi-face");
    let out = d.join("report.json");
    let (ok, text) = holoface(&[
        "multi-face",
        "--counts",
        "3",
        "--frames",
        "120",
        "--out",
        out.to_str().unwrap(),
    ]);
    assert!(ok, "{text}");
    let report: serde_json::Value = serde_json::from_slice(&std::fs::read(&out).unwrap()).unwrap();
    let scene = &report["scenes"][0];
    assert_eq!(scene["faces"], 3, "{scene}");
    assert_eq!(scene["tracks_at_once"], 3, "all three tracked together: {scene}");
    assert_eq!(
        scene["id_switches"], 0,
        "no face ever takes another's id: {scene}"
    );
    let runs = scene["detector_runs"].as_u64().unwrap();
    assert!(
        (1..120).contains(&runs),
        "the detector runs on a cadence, not every frame: {scene}"
    );
    for face in scene["per_face"].as_array().unwrap() {
        let (together, alone) = (
            face["nme49_pct"].as_f64().unwrap(),
            face["nme49_alone_pct"].as_f64().unwrap(),
        );
        assert!(together > 0.0 && alone > 0.0, "{face}");
        assert!(
            (together / alone - 1.0).abs() <= 0.10,
            "each face as accurate as alone (within 10 %): {face}"
        );
        assert!(face["tracked_frames_pct"].as_f64().unwrap() >= 80.0, "{face}");
    }
}

#[test]
fn multi_face_rejects_impossible_scenes() {
    for counts in ["0", "6"] {
        let (ok, text) = holoface(&["multi-face", "--counts", counts, "--frames", "1"]);
        assert!(!ok && text.contains("1..=5"), "--counts {counts}: {text}");
    }
}

#[test]
fn track_follows_every_face_of_a_recorded_scene_with_stable_ids() {
    let d = tmp("multi-face-track");
    let seq = d.join("seq");
    let (ok, text) = holoface(&[
        "multi-face",
        "--counts",
        "3",
        "--frames",
        "30",
        "--write-sequence",
        seq.to_str().unwrap(),
        "--out",
        d.join("report.json").to_str().unwrap(),
    ]);
    assert!(ok, "{text}");
    assert!(text.contains("wrote 30 frames of the 3-face scene"), "{text}");
    let out = d.join("track.jsonl");
    let (ok, text) = holoface(&[
        "track",
        "--source",
        seq.join("sequence.mp4").to_str().unwrap(),
        "--poses",
        seq.join("poses.jsonl").to_str().unwrap(),
        "--max-faces",
        "3",
        "--out",
        out.to_str().unwrap(),
    ]);
    assert!(ok, "{text}");
    let lines: Vec<serde_json::Value> = std::fs::read_to_string(&out)
        .unwrap()
        .lines()
        .map(|l| serde_json::from_str(l).unwrap())
        .collect();
    assert_eq!(lines.len(), 30);
    let truth: Vec<serde_json::Value> = std::fs::read_to_string(seq.join("truth.jsonl"))
        .unwrap()
        .lines()
        .map(|l| serde_json::from_str(l).unwrap())
        .collect();
    // Each face's nose tip (point 30) is followed (within 20 px; the faces are 90 px apart) by one id while
    // it is tracked; an id changes only after a frame where the face was lost (the third face is the
    // validation set's hardest for KRFWS, whose failure detector rejects it now and then, alone too), and no
    // id ever follows two faces.
    let nose = |lm: &serde_json::Value| (lm[30][0].as_f64().unwrap(), lm[30][1].as_f64().unwrap());
    let mut last: [Option<u64>; 3] = [None; 3];
    let mut tracked = [0usize; 3];
    let mut owner = std::collections::HashMap::new();
    for (g, t) in lines.iter().zip(&truth) {
        let faces = g["faces"].as_array().unwrap();
        assert!(faces.len() <= 3, "{g}");
        for (k, truth_lm) in t["faces_landmarks_px"].as_array().unwrap().iter().enumerate() {
            let (tx, ty) = nose(truth_lm);
            let id = faces
                .iter()
                .find(|f| {
                    let (nx, ny) = nose(&f["landmarks_px"]);
                    (nx - tx).hypot(ny - ty) < 20.0
                })
                .map(|f| f["id"].as_u64().unwrap());
            if let Some(id) = id {
                tracked[k] += 1;
                assert_eq!(
                    *owner.entry(id).or_insert(k),
                    k,
                    "frame {}: id {id} follows two faces",
                    g["frame"]
                );
                if let Some(prev) = last[k] {
                    assert_eq!(
                        prev, id,
                        "frame {}: face {k} changed id while tracked",
                        g["frame"]
                    );
                }
            }
            last[k] = id;
        }
    }
    assert_eq!(
        &tracked[..2],
        [30, 30],
        "the two easier faces are tracked in every frame"
    );
    assert!(
        tracked[2] >= 15,
        "the third face tracked in {} of 30 frames",
        tracked[2]
    );
}

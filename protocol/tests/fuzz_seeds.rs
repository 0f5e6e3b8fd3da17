//! Writes a seed corpus for the cargo-fuzz targets in `fuzz/` (valid
//! encodings of every message and a small recording), so the fuzzers start
//! from deep inside the format instead of from random bytes.
//!
//! `cargo test -p holoface-protocol --test integration fuzz_seeds:: -- --ignored`
//! writes into `fuzz/corpus/<target>/` (git-ignored).
#![allow(clippy::unwrap_used)] // test helpers; a panic is a test failure

use std::fs;
use std::path::Path;

use bytes::{Bytes, BytesMut};
use holoface_protocol::{
    CameraIntrinsics, ClientHello, CloseCode, Crop, CropEncoding, DropReason, ErrorMsg, FramePayload,
    FrameRecord, FrameReply, FrameRequest, Goaway, Message, RecordingHeader, RecordingWriter, ReplyChannel,
    ReplyOutcome, ServerWelcome, encode_framed,
};

fn messages() -> Vec<Message> {
    vec![
        ClientHello {
            version: 1,
            token: "secret".into(),
            client_name: "headset-1".into(),
            encodings: vec![CropEncoding::Jpeg, CropEncoding::Raw],
            max_in_flight: 2,
        }
        .into(),
        ServerWelcome {
            version: 1,
            model_id: "dan-1stage".into(),
            model_version: "2026.1".into(),
            landmark_count: 3,
            crop_size: 112,
            mean_shape: vec![[30.0, 40.0], [80.0, 40.0], [56.0, 90.0]],
            face_threshold: 0.1,
            encoding: CropEncoding::Raw,
            reply_channel: ReplyChannel::Datagram,
            max_in_flight: 2,
            max_frame_age_ms: 66,
        }
        .into(),
        FrameRequest {
            track_id: 0,
            frame_id: 7,
            captured_at_us: 1_000_000,
            deadline_ms: 66,
            crop: Crop::raw(8, 8, vec![128_u8; 64]),
        }
        .into(),
        FrameReply {
            track_id: 0,
            frame_id: 7,
            outcome: ReplyOutcome::Landmarks {
                landmarks: vec![[31.0, 41.0], [79.5, 40.5]],
                face_prob: 0.97,
                queue_us: 150,
                infer_us: 4200,
            },
        }
        .into(),
        FrameReply {
            track_id: 0,
            frame_id: 8,
            outcome: ReplyOutcome::Dropped {
                reason: DropReason::Superseded,
            },
        }
        .into(),
        Goaway {
            reason: CloseCode::ShuttingDown,
            text: "draining".into(),
        }
        .into(),
        ErrorMsg {
            code: CloseCode::Unauthorized,
            text: "bad token".into(),
        }
        .into(),
    ]
}

fn records() -> Vec<FrameRecord> {
    vec![
        FrameRecord {
            timestamp_us: 33_333,
            camera_to_world: [
                1.0, 0.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 0.0, 1.0,
            ],
            payload: FramePayload::Crop {
                image_from_crop: [2.0, 0.1, 100.0, 50.0],
                crop: Crop::raw(4, 4, vec![9_u8; 16]),
            },
            ground_truth: Some(vec![[10.0, 20.0], [30.0, 40.0]]),
            face_present: Some(true),
        },
        FrameRecord {
            timestamp_us: 66_666,
            camera_to_world: [0.5; 16],
            payload: FramePayload::FullFrame {
                width: 6,
                height: 2,
                encoding: CropEncoding::Raw,
                data: Bytes::from(vec![1_u8; 12]),
            },
            ground_truth: None,
            face_present: None,
        },
    ]
}

fn write(dir: &Path, name: &str, bytes: &[u8]) {
    fs::create_dir_all(dir).unwrap();
    fs::write(dir.join(name), bytes).unwrap();
}

#[test]
#[ignore = "writes files; run explicitly to refresh the fuzz seed corpus"]
fn write_fuzz_seeds() {
    let corpus = Path::new(env!("CARGO_MANIFEST_DIR")).join("../fuzz/corpus");
    let mut stream = BytesMut::from(&[0_u8][..]); // first byte: chunk size for decode_framed
    for (i, m) in messages().iter().enumerate() {
        write(
            &corpus.join("decode_message"),
            &format!("seed-{i}"),
            &m.to_bytes().unwrap(),
        );
        encode_framed(m, &mut stream).unwrap();
    }
    write(&corpus.join("decode_framed"), "seed-all", &stream);

    let header = RecordingHeader {
        intrinsics: CameraIntrinsics {
            fx: 500.0,
            fy: 500.0,
            cx: 320.0,
            cy: 240.0,
            width: 640,
            height: 480,
        },
        source: "seed".into(),
        created_unix_ms: 1_700_000_000_000,
    };
    let mut w = RecordingWriter::new(Vec::new(), &header).unwrap();
    for (i, r) in records().iter().enumerate() {
        w.write_record(r).unwrap();
        let mut body = BytesMut::new();
        r.encode_body(&mut body).unwrap();
        write(&corpus.join("decode_record_body"), &format!("seed-{i}"), &body);
    }
    write(&corpus.join("read_recording"), "seed-file", &w.finish().unwrap());
}

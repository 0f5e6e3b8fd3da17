//! Codec benchmarks: the hand-written codec vs postcard + serde_bytes on
//! equivalent structs, for a raw 112x112 `FrameRequest` and a 68-landmark
//! `FrameReply`; plus bytes on the wire per crop encoding (printed first).
//!
//! `cargo bench -p holoface-protocol -- --warm-up-time 1 --measurement-time 3`
#![allow(clippy::unwrap_used)] // bench setup; a panic is a failed run

use std::hint::black_box;

use bytes::{Bytes, BytesMut};
use criterion::{Criterion, Throughput, criterion_group};
use holoface_protocol::{
    CROP_PIXELS, CROP_SIZE, Crop, CropEncoding, FrameReply, FrameRequest, Message, ReplyOutcome,
};
use image::codecs::jpeg::JpegEncoder;
use image::codecs::png::{CompressionType, FilterType, PngEncoder};
use image::{ExtendedColorType, ImageEncoder};
use serde::{Deserialize, Serialize};

// ------------------------------------------------------------ test data

/// A deterministic, real-looking 112x112 gray face crop: a smooth vertical
/// and horizontal gradient, a bright face ellipse, dark blobs for eyes,
/// brows, nostrils and mouth, and per-pixel sensor noise.
fn synthetic_crop() -> Vec<u8> {
    let mut state: u32 = 0x9e37_79b9;
    let mut noise = move || {
        // xorshift32
        state ^= state << 13;
        state ^= state >> 17;
        state ^= state << 5;
        (state >> 24) as f32 / 255.0 - 0.5
    };
    let blob = |x: f32, y: f32, cx: f32, cy: f32, sx: f32, sy: f32| {
        (-(((x - cx) / sx).powi(2) + ((y - cy) / sy).powi(2)) / 2.0).exp()
    };
    let n = CROP_SIZE as f32;
    let mut out = Vec::with_capacity(CROP_PIXELS);
    for y in 0..CROP_SIZE {
        for x in 0..CROP_SIZE {
            let (xf, yf) = (x as f32, y as f32);
            let mut v = 70.0 + 50.0 * xf / n + 30.0 * yf / n; // background gradient
            v += 70.0 * blob(xf, yf, 56.0, 60.0, 30.0, 40.0); // face
            v -= 60.0 * blob(xf, yf, 38.0, 46.0, 6.0, 3.5); // eyes
            v -= 60.0 * blob(xf, yf, 74.0, 46.0, 6.0, 3.5);
            v -= 35.0 * blob(xf, yf, 37.0, 36.0, 9.0, 2.0); // brows
            v -= 35.0 * blob(xf, yf, 75.0, 36.0, 9.0, 2.0);
            v -= 30.0 * blob(xf, yf, 51.0, 70.0, 2.5, 2.0); // nostrils
            v -= 30.0 * blob(xf, yf, 61.0, 70.0, 2.5, 2.0);
            v -= 45.0 * blob(xf, yf, 56.0, 86.0, 13.0, 3.0); // mouth
            v += 12.0 * noise(); // sensor noise
            out.push(v.clamp(0.0, 255.0) as u8);
        }
    }
    out
}

fn png(pixels: &[u8], compression: CompressionType) -> Vec<u8> {
    let mut out = Vec::new();
    PngEncoder::new_with_quality(&mut out, compression, FilterType::Adaptive)
        .write_image(pixels, CROP_SIZE as u32, CROP_SIZE as u32, ExtendedColorType::L8)
        .unwrap();
    out
}

fn jpeg(pixels: &[u8], quality: u8) -> Vec<u8> {
    let mut out = Vec::new();
    JpegEncoder::new_with_quality(&mut out, quality)
        .write_image(pixels, CROP_SIZE as u32, CROP_SIZE as u32, ExtendedColorType::L8)
        .unwrap();
    out
}

fn request(encoding: CropEncoding, data: Vec<u8>) -> Message {
    FrameRequest {
        track_id: 0,
        frame_id: 123_456,
        captured_at_us: 1_700_000_000_000_000,
        deadline_ms: 66,
        crop: Crop {
            encoding,
            width: CROP_SIZE as u16,
            height: CROP_SIZE as u16,
            data: data.into(),
        },
    }
    .into()
}

fn landmarks68() -> Vec<[f32; 2]> {
    (0..68)
        .map(|i| [20.0 + i as f32 * 1.1, 30.0 + (i as f32 * 0.7).sin() * 25.0])
        .collect()
}

fn reply() -> Message {
    FrameReply {
        track_id: 0,
        frame_id: 123_456,
        outcome: ReplyOutcome::Landmarks {
            landmarks: landmarks68(),
            face_prob: 0.97,
            queue_us: 850,
            infer_us: 4_200,
        },
    }
    .into()
}

// ------------------------------------------------------------ postcard peer

/// The same fields as `Message::FrameRequest`, serde-style, pixels owned.
#[derive(Serialize, Deserialize, Debug, PartialEq)]
enum PcMessageOwned {
    FrameRequest {
        frame_id: u64,
        captured_at_us: u64,
        deadline_ms: u16,
        encoding: u8,
        width: u16,
        height: u16,
        #[serde(with = "serde_bytes")]
        data: Vec<u8>,
    },
}

/// Pixels borrowed from the input buffer (zero-copy, lifetime-bound).
#[derive(Serialize, Deserialize, Debug, PartialEq)]
enum PcMessageBorrowed<'a> {
    FrameRequest {
        frame_id: u64,
        captured_at_us: u64,
        deadline_ms: u16,
        encoding: u8,
        width: u16,
        height: u16,
        #[serde(borrow, with = "serde_bytes")]
        data: &'a [u8],
    },
}

/// The same fields as `Message::FrameReply`.
#[derive(Serialize, Deserialize, Debug, PartialEq)]
enum PcOutcome {
    Landmarks {
        landmarks: Vec<[f32; 2]>,
        face_prob: f32,
        queue_us: u32,
        infer_us: u32,
    },
    Dropped {
        reason: u8,
    },
}

#[derive(Serialize, Deserialize, Debug, PartialEq)]
struct PcReply {
    frame_id: u64,
    outcome: PcOutcome,
}

fn pc_request(data: &[u8]) -> PcMessageOwned {
    PcMessageOwned::FrameRequest {
        frame_id: 123_456,
        captured_at_us: 1_700_000_000_000_000,
        deadline_ms: 66,
        encoding: 0,
        width: CROP_SIZE as u16,
        height: CROP_SIZE as u16,
        data: data.to_vec(),
    }
}

fn pc_reply() -> PcReply {
    PcReply {
        frame_id: 123_456,
        outcome: PcOutcome::Landmarks {
            landmarks: landmarks68(),
            face_prob: 0.97,
            queue_us: 850,
            infer_us: 4_200,
        },
    }
}

// ------------------------------------------------------------ wire sizes

fn print_wire_sizes() {
    let pixels = synthetic_crop();
    let mut rows: Vec<(String, usize, usize)> = Vec::new();
    let mut push = |name: String, encoding: CropEncoding, data: Vec<u8>| {
        let payload = data.len();
        rows.push((name, payload, request(encoding, data).encoded_len()));
    };
    push("raw gray8".into(), CropEncoding::Raw, pixels.clone());
    push(
        "PNG (default)".into(),
        CropEncoding::Png,
        png(&pixels, CompressionType::Default),
    );
    push(
        "PNG (best)".into(),
        CropEncoding::Png,
        png(&pixels, CompressionType::Best),
    );
    for q in [75, 85, 95] {
        push(format!("JPEG q{q}"), CropEncoding::Jpeg, jpeg(&pixels, q));
    }
    println!("wire sizes, 112x112 synthetic gray crop (FrameRequest = tag + 27 B header + payload):");
    println!(
        "{:<16} {:>10} {:>14} {:>10}",
        "encoding", "payload B", "FrameRequest B", "datagrams"
    );
    for (name, payload, total) in &rows {
        // 1200 B is the QUIC minimum; quinn only guarantees "a little over a kilobyte".
        println!(
            "{name:<16} {payload:>10} {total:>14} {:>10}",
            total.div_ceil(1200)
        );
    }
    let r = reply();
    let pc = postcard::to_allocvec(&pc_reply()).unwrap();
    let pcr = postcard::to_allocvec(&pc_request(&pixels)).unwrap();
    println!(
        "FrameReply (68 landmarks): {} B (postcard peer {} B)",
        r.encoded_len(),
        pc.len()
    );
    println!(
        "FrameRequest raw: {} B (postcard peer {} B)",
        request(CropEncoding::Raw, pixels).encoded_len(),
        pcr.len()
    );
    println!();
}

// ------------------------------------------------------------ benches

fn bench_request(c: &mut Criterion) {
    let pixels = synthetic_crop();
    let msg = request(CropEncoding::Raw, pixels.clone());
    let wire = msg.to_bytes().unwrap();
    let pc_msg = pc_request(&pixels);
    let pc_wire = postcard::to_allocvec(&pc_msg).unwrap();

    let mut g = c.benchmark_group("frame_request_raw");
    g.throughput(Throughput::Bytes(wire.len() as u64));

    let mut buf = BytesMut::with_capacity(wire.len());
    g.bench_function("holoface/encode", |b| {
        b.iter(|| {
            buf.clear();
            black_box(&msg).encode(&mut buf).unwrap();
            black_box(buf.len())
        })
    });
    let mut out = vec![0_u8; pc_wire.len() + 64];
    g.bench_function("postcard/encode", |b| {
        b.iter(|| postcard::to_slice(black_box(&pc_msg), &mut out).unwrap().len())
    });
    g.bench_function("holoface/decode", |b| {
        b.iter(|| Message::decode(black_box(wire.clone())).unwrap())
    });
    g.bench_function("postcard/decode_owned", |b| {
        b.iter(|| postcard::from_bytes::<PcMessageOwned>(black_box(&pc_wire)).unwrap())
    });
    g.bench_function("postcard/decode_borrowed", |b| {
        b.iter(|| postcard::from_bytes::<PcMessageBorrowed<'_>>(black_box(&pc_wire)).unwrap())
    });
    g.finish();
}

fn bench_reply(c: &mut Criterion) {
    let msg = reply();
    let wire: Bytes = msg.to_bytes().unwrap();
    let pc_msg = pc_reply();
    let pc_wire = postcard::to_allocvec(&pc_msg).unwrap();

    let mut g = c.benchmark_group("frame_reply_68");
    g.throughput(Throughput::Bytes(wire.len() as u64));
    let mut buf = BytesMut::with_capacity(wire.len());
    g.bench_function("holoface/encode", |b| {
        b.iter(|| {
            buf.clear();
            black_box(&msg).encode(&mut buf).unwrap();
            black_box(buf.len())
        })
    });
    let mut out = vec![0_u8; pc_wire.len() + 64];
    g.bench_function("postcard/encode", |b| {
        b.iter(|| postcard::to_slice(black_box(&pc_msg), &mut out).unwrap().len())
    });
    g.bench_function("holoface/decode", |b| {
        b.iter(|| Message::decode(black_box(wire.clone())).unwrap())
    });
    g.bench_function("postcard/decode", |b| {
        b.iter(|| postcard::from_bytes::<PcReply>(black_box(&pc_wire)).unwrap())
    });
    g.finish();
}

criterion_group!(benches, bench_request, bench_reply);

fn main() {
    print_wire_sizes();
    benches();
    Criterion::default().configure_from_args().final_summary();
}

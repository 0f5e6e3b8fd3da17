//! KRFWS model loading: arbitrary bytes must never panic. The input is tried as it is and re-sealed
//! with a valid header and CRC-32 (so the structural checks, not just the checksum, are exercised);
//! whatever loads must survive a round trip and an alignment on a small synthetic frame.
#![no_main]

use holoface_models::geometry::{Point2, Rect};
use holoface_models::image::GrayImage;
use holoface_models::krfws::format::{FORMAT_VERSION, MAGIC};
use holoface_models::krfws::{Krfws, KrfwsScratch, N_POINTS};
use libfuzzer_sys::fuzz_target;

fn seal(payload: &[u8]) -> Vec<u8> {
    let mut out = Vec::with_capacity(payload.len() + 20);
    out.extend_from_slice(&MAGIC);
    out.extend_from_slice(&FORMAT_VERSION.to_le_bytes());
    out.extend_from_slice(&(payload.len() as u32).to_le_bytes());
    out.extend_from_slice(payload);
    let crc = crc32fast::hash(&out);
    out.extend_from_slice(&crc.to_le_bytes());
    out
}

fn exercise(model: &Krfws) {
    let bytes = model.to_bytes().expect("a loaded model is within the limit");
    let again = Krfws::from_bytes(&bytes).expect("a loaded model re-serialises");
    assert_eq!(&again, model);
    let img = GrayImage::from_vec((0..64 * 64).map(|i| (i * 7 % 251) as u8).collect(), 64, 64)
        .expect("64x64 image");
    let bbox = Rect {
        x0: 16.0,
        y0: 16.0,
        x1: 48.0,
        y1: 48.0,
    };
    let init = model.init_from_box(&bbox);
    let mut out = [Point2::default(); N_POINTS];
    let _ = model.align(&img.view(), &init, &mut KrfwsScratch::new(), &mut out);
}

fuzz_target!(|data: &[u8]| {
    if let Ok(m) = Krfws::from_bytes(data) {
        exercise(&m);
    }
    if let Ok(m) = Krfws::from_bytes(&seal(data)) {
        exercise(&m);
    }
});

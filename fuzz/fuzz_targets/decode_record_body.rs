//! Decodes arbitrary bytes as a frame-record body: must never panic, and a
//! decoded record must re-encode to exactly the same bytes.
#![no_main]

use bytes::{Bytes, BytesMut};
use holoface_protocol::FrameRecord;
use libfuzzer_sys::fuzz_target;

fuzz_target!(|data: &[u8]| {
    if let Ok(rec) = FrameRecord::decode_body(Bytes::copy_from_slice(data)) {
        let mut out = BytesMut::new();
        rec.encode_body(&mut out).expect("a decoded record re-encodes");
        assert_eq!(&out[..], data, "re-encoding changed the bytes");
    }
});

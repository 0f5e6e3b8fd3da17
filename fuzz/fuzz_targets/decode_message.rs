//! Whole-buffer message decoding: must never panic, and anything that
//! decodes must re-encode to exactly the same bytes.
#![no_main]

use bytes::{Bytes, BytesMut};
use holoface_protocol::Message;
use libfuzzer_sys::fuzz_target;

fuzz_target!(|data: &[u8]| {
    let input = Bytes::copy_from_slice(data);
    if let Ok(msg) = Message::decode(input) {
        let mut out = BytesMut::new();
        msg.encode(&mut out).expect("a decoded message re-encodes");
        assert_eq!(&out[..], data, "re-encoding changed the bytes");
        assert_eq!(msg.encoded_len(), data.len());
    }
});

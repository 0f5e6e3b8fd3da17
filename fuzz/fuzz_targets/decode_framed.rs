//! Length-prefixed stream decoding, fed in fuzzer-chosen chunk sizes: must
//! never panic, never report `Short` (that is `Ok(None)` here), and must
//! decode the same messages however the stream is chunked.
#![no_main]

use bytes::BytesMut;
use holoface_protocol::{Message, decode_framed};
use libfuzzer_sys::fuzz_target;

fn decode_all(chunks: &mut dyn Iterator<Item = &[u8]>) -> (Vec<Message>, bool) {
    let mut rx = BytesMut::new();
    let mut out = Vec::new();
    for chunk in chunks {
        rx.extend_from_slice(chunk);
        loop {
            match decode_framed(&mut rx) {
                Ok(Some(m)) => out.push(m),
                Ok(None) => break,
                Err(e) => {
                    assert!(!e.is_short(), "decode_framed returned Short");
                    return (out, true);
                }
            }
        }
    }
    (out, false)
}

fuzz_target!(|data: &[u8]| {
    let Some((&chunk, stream)) = data.split_first() else {
        return;
    };
    let chunk = usize::from(chunk.max(1));
    let whole = decode_all(&mut std::iter::once(stream));
    let chunked = decode_all(&mut stream.chunks(chunk));
    assert_eq!(whole, chunked, "chunking changed the result");
});

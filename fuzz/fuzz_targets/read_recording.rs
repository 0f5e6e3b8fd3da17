//! Streams arbitrary bytes through `RecordingReader` to the end: must never
//! panic, must stop after the first error, and must agree with
//! `RecordingHeader::decode` about the header.
#![no_main]

use std::io::Cursor;

use holoface_protocol::{RecordingHeader, RecordingReader};
use libfuzzer_sys::fuzz_target;

fuzz_target!(|data: &[u8]| {
    let from_slice = RecordingHeader::decode(data);
    match RecordingReader::new(Cursor::new(data)) {
        Ok(mut reader) => {
            assert_eq!(from_slice.ok().as_ref(), Some(reader.header()));
            let mut n = 0_u64;
            for rec in reader.by_ref() {
                if rec.is_err() {
                    break;
                }
                n += 1;
            }
            assert_eq!(reader.frames_read(), n);
            assert!(matches!(reader.next_record(), Ok(None)), "reader is fused");
        }
        Err(_) => assert!(from_slice.is_err()),
    }
});

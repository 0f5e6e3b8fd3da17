//! Hostile length prefixes must not make the decoders allocate: this test
//! binary installs a counting global allocator and checks the largest single
//! allocation made while decoding.
#![allow(unsafe_code)] // GlobalAlloc is an unsafe trait; this file only forwards to System.

use std::alloc::{GlobalAlloc, Layout, System};
use std::cell::Cell;

use bytes::{Bytes, BytesMut};
use holoface_protocol::limits::MAX_RECORD_LEN;
use holoface_protocol::{
    CameraIntrinsics, DecodeError, Message, RecordingError, RecordingHeader, RecordingReader, decode_framed,
};

thread_local! {
    static LARGEST: Cell<usize> = const { Cell::new(0) };
}

struct Counting;

// SAFETY: forwards every call to `System` unchanged; only records sizes in a
// const-initialised thread-local `Cell`, which never allocates.
unsafe impl GlobalAlloc for Counting {
    unsafe fn alloc(&self, layout: Layout) -> *mut u8 {
        note(layout.size());
        // SAFETY: same contract as the caller's.
        unsafe { System.alloc(layout) }
    }

    unsafe fn alloc_zeroed(&self, layout: Layout) -> *mut u8 {
        note(layout.size());
        // SAFETY: same contract as the caller's.
        unsafe { System.alloc_zeroed(layout) }
    }

    unsafe fn dealloc(&self, ptr: *mut u8, layout: Layout) {
        // SAFETY: same contract as the caller's.
        unsafe { System.dealloc(ptr, layout) }
    }

    unsafe fn realloc(&self, ptr: *mut u8, layout: Layout, new_size: usize) -> *mut u8 {
        note(new_size);
        // SAFETY: same contract as the caller's.
        unsafe { System.realloc(ptr, layout, new_size) }
    }
}

fn note(size: usize) {
    let _ = LARGEST.try_with(|l| l.set(l.get().max(size)));
}

#[global_allocator]
static ALLOC: Counting = Counting;

/// Runs `f` and returns its result and the largest single allocation it made
/// on this thread.
fn largest_alloc<T>(f: impl FnOnce() -> T) -> (T, usize) {
    LARGEST.with(|l| l.set(0));
    let out = f();
    (out, LARGEST.with(Cell::get))
}

#[test]
fn hostile_message_prefixes_allocate_nothing_big() {
    let inputs: Vec<Bytes> = vec![
        // token: 65535 bytes announced
        Bytes::from_static(&[0x01, 1, 0, 0xff, 0xff, b'a']),
        // reply: 65535 landmarks announced
        Bytes::from_static(&[0x04, 0, 0, 0, 0, 0, 0, 0, 0, 0, 0xff, 0xff, 0, 0]),
        // request: 4 GiB crop announced
        Bytes::from_static(&[
            0x03, 0, 0, 0, 0, 0, 0, 0, 0, 0, 0, 0, 0, 0, 0, 0, 0, 0, 0, 1, 8, 0, 8, 0, 0xff, 0xff, 0xff, 0xff,
        ]),
    ];
    for input in inputs {
        let (res, largest) = largest_alloc(|| Message::decode(input.clone()));
        assert!(matches!(res, Err(DecodeError::TooLarge { .. })), "{res:?}");
        assert!(largest < 64, "decoding {input:?} allocated {largest} bytes");
    }

    let (res, largest) = largest_alloc(|| {
        let mut rx = BytesMut::from(&[0xff, 0xff, 0xff, 0xff, 1, 2, 3][..]);
        decode_framed(&mut rx)
    });
    assert!(matches!(res, Err(DecodeError::TooLarge { field: "message", .. })));
    assert!(largest < 64, "framed decode allocated {largest} bytes");
}

#[test]
fn lying_record_lengths_allocate_only_what_arrives() {
    let header = RecordingHeader {
        intrinsics: CameraIntrinsics {
            fx: 500.0,
            fy: 500.0,
            cx: 320.0,
            cy: 240.0,
            width: 640,
            height: 480,
        },
        source: "alloc test".into(),
        created_unix_ms: 0,
    };
    let mut file = header.encode().unwrap().to_vec();
    let header_len = file.len();

    // Over the limit: refused from the prefix alone.
    file.extend_from_slice(&[0xff, 0xff, 0xff, 0xff, 0, 0, 0, 0, 1, 2, 3]);
    let (res, largest) = largest_alloc(|| RecordingReader::new(&file[..]).and_then(|mut r| r.next_record()));
    assert!(
        matches!(res, Err(RecordingError::TooLarge { field: "record", .. })),
        "{res:?}"
    );
    assert!(largest < 4096, "allocated {largest} bytes");

    // Exactly at the limit (32 MiB) but only 3 bytes follow: Truncated, and
    // the buffer grew only to the first chunk, not to 32 MiB.
    file.truncate(header_len);
    file.extend_from_slice(&u32::try_from(MAX_RECORD_LEN).unwrap().to_le_bytes());
    file.extend_from_slice(&[0, 0, 0, 0, 1, 2, 3]);
    let (res, largest) = largest_alloc(|| RecordingReader::new(&file[..]).and_then(|mut r| r.next_record()));
    assert!(
        matches!(res, Err(RecordingError::Truncated { record_index: 0, .. })),
        "{res:?}"
    );
    assert!(
        largest <= 64 * 1024,
        "allocated {largest} bytes for a 3-byte record"
    );
}

//! Every close code and drop reason has one distinct snake_case name (metric labels, logs and tools read
//! them from here, nowhere else).

use std::collections::HashSet;

use holoface_protocol::{CloseCode, DropReason};

fn check(names: &[&'static str]) {
    let unique: HashSet<_> = names.iter().collect();
    assert_eq!(unique.len(), names.len(), "duplicate names in {names:?}");
    for n in names {
        assert!(
            !n.is_empty() && n.chars().all(|c| c.is_ascii_lowercase() || c == '_'),
            "{n:?} is not snake_case"
        );
    }
}

#[test]
fn close_code_names_are_distinct_snake_case() {
    let names: Vec<_> = CloseCode::ALL.iter().map(|c| c.name()).collect();
    check(&names);
    assert_eq!(CloseCode::ShuttingDown.name(), "shutting_down");
}

#[test]
fn drop_reason_names_are_distinct_snake_case() {
    let names: Vec<_> = DropReason::ALL.iter().map(|r| r.name()).collect();
    check(&names);
    assert_eq!(DropReason::BadCrop.name(), "bad_crop");
}

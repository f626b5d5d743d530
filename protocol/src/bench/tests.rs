//! Checksums, latency percentiles and the synthetic descriptor of the IPC benchmark.

use super::*;
use crate::messages::DESCRIPTOR_LEN;

#[test]
fn checksum_sees_order_and_content() {
    let a: Vec<_> = (0..100).map(|i| synthetic_record(1, i)).collect();
    let mut b = a.clone();
    assert_eq!(records_checksum(&a), records_checksum(&b));
    b.swap(3, 4);
    assert_ne!(records_checksum(&a), records_checksum(&b));
    let mut c = a.clone();
    c[50].colour[2] += 1e-6;
    assert_ne!(records_checksum(&a), records_checksum(&c));
}

#[test]
fn latency_summary_percentiles() {
    let s = LatencySummary::from_ns((1..=100).map(|v| v * 1000).collect());
    assert_eq!(s.samples, 100);
    assert!((s.median_us - 51.0).abs() <= 1.0, "{}", s.median_us);
    assert!((s.p99_us - 99.0).abs() <= 1.0, "{}", s.p99_us);
    assert_eq!(s.max_us, 100.0);
}

#[test]
fn synthetic_descriptor_is_normalised() {
    let d = synthetic_descriptor(7);
    assert!((d.descriptor_norm() - 1.0).abs() < 1e-5);
    assert_eq!(d.descriptor.len(), DESCRIPTOR_LEN);
}

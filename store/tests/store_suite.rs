//! The store suite over every backend: `memory://`, a temporary directory (as a plain path and as
//! `file://`), and an S3-compatible server when `VLF_TEST_S3_URL` is set (`.ci/run` starts one on
//! loopback; see the crate README).

#[macro_use]
mod suite;

per_backend! {
    put_get_list_delete => crate::suite::put_get_list_delete,
    put_new_is_create_only => crate::suite::put_new_is_create_only,
    invalid_keys_are_refused => crate::suite::invalid_keys_are_refused,
    blobs_through_the_store => crate::suite::blobs_through_the_store,
    job_lifecycle => crate::suite::job_lifecycle,
    crash_between_blobs_and_manifest => crate::suite::crash_between_blobs_and_manifest,
    corrupted_manifest => crate::suite::corrupted_manifest,
    concurrent_writers => crate::suite::concurrent_writers,
    unrepresentable_radiance => crate::suite::unrepresentable_radiance,
}

//! The store suite over every backend: `memory://`, a temporary directory (as a plain path and as
//! `file://`), and an S3-compatible server when `VLF_TEST_S3_URL` is set (`.ci/run` starts one on
//! loopback; see the crate README).

mod suite;

use suite::Opener;

/// One test per suite case and backend, so a failure names both.
macro_rules! backend {
    ($name:ident, $opener:expr) => {
        mod $name {
            use super::*;

            fn run(case: &str, f: fn(&Opener)) {
                let opener: Option<Opener> = ($opener)(case);
                if let Some(o) = opener {
                    f(&o);
                }
            }

            #[test]
            fn put_get_list_delete() {
                run("put-get", suite::put_get_list_delete);
            }
            #[test]
            fn put_new_is_create_only() {
                run("put-new", suite::put_new_is_create_only);
            }
            #[test]
            fn invalid_keys_are_refused() {
                run("keys", suite::invalid_keys_are_refused);
            }
            #[test]
            fn blobs_through_the_store() {
                run("blobs", suite::blobs_through_the_store);
            }
            #[test]
            fn job_lifecycle() {
                run("lifecycle", suite::job_lifecycle);
            }
            #[test]
            fn crash_between_blobs_and_manifest() {
                run("crash", suite::crash_between_blobs_and_manifest);
            }
            #[test]
            fn corrupted_manifest() {
                run("manifest", suite::corrupted_manifest);
            }
            #[test]
            fn concurrent_writers() {
                run("threads", suite::concurrent_writers);
            }
            #[test]
            fn unrepresentable_radiance() {
                run("unrepresentable", suite::unrepresentable_radiance);
            }
        }
    };
}

backend!(memory, |_| Some(Opener::memory()));
backend!(path, |_| Some(Opener::file(false)));
backend!(file_url, |_| Some(Opener::file(true)));
backend!(s3, Opener::s3);

//! A local store runs its file calls on a few threads, however many calls a bulk write keeps in
//! flight (see `file_threads`). A test binary of its own: it counts the process's threads.

use vlf_store::{IN_FLIGHT, Put, Store, file_threads};

/// The threads of this process, as the kernel lists them.
#[cfg(target_os = "linux")]
fn threads() -> usize {
    std::fs::read_dir("/proc/self/task").map_or(0, |tasks| tasks.count())
}

#[cfg(target_os = "linux")]
#[test]
fn a_bulk_write_to_a_directory_starts_a_bounded_number_of_threads() {
    let dir = tempfile::tempdir().unwrap();
    let store = Store::open(dir.path().to_str().unwrap()).unwrap();
    let before = threads();
    let count = 4 * IN_FLIGHT;
    let puts: Vec<Put> = (0..count)
        .map(|i| Put {
            key: format!("burst/{i:05}.bin"),
            bytes: vec![i as u8; 4096].into(),
            create_only: true,
        })
        .collect();
    store.put_all(puts).unwrap();
    // Idle threads stay a while after the call: every one it started is still there.
    let started = threads() - before;
    // The runtime's two async workers, which start with the first call, and its file threads.
    assert!(
        started <= 2 + file_threads(),
        "{count} writes started {started} threads"
    );
    let keys: Vec<String> = (0..count).map(|i| format!("burst/{i:05}.bin")).collect();
    let read = store.get_all(&keys).unwrap();
    assert!(read.iter().enumerate().all(|(i, b)| b[..] == vec![i as u8; 4096][..]));
}

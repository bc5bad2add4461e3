//! A blocking read of a few objects of a local directory reads them on the caller's thread
//! (`READ_HERE`): it starts none of the store's threads, so it cannot queue behind the calls they
//! have in hand. A test binary of its own: it counts the process's threads.

use vlf_store::{READ_HERE, Store};

/// The threads of this process, as the kernel lists them.
#[cfg(target_os = "linux")]
fn threads() -> usize {
    std::fs::read_dir("/proc/self/task").map_or(0, |tasks| tasks.count())
}

#[cfg(target_os = "linux")]
#[test]
fn a_few_reads_of_a_directory_start_no_store_thread() {
    let dir = tempfile::tempdir().unwrap();
    // Written behind the store's back, so that the store has made no call yet.
    let keys: Vec<String> = (0..=READ_HERE).map(|i| format!("few/{i:02}.bin")).collect();
    std::fs::create_dir_all(dir.path().join("few")).unwrap();
    for (i, key) in keys.iter().enumerate() {
        std::fs::write(dir.path().join(key), vec![i as u8; 1000]).unwrap();
    }
    let store = Store::open(dir.path().to_str().unwrap()).unwrap();
    let before = threads();
    let few = &keys[..READ_HERE];
    for _ in 0..3 {
        let read = store.get_all(few).unwrap();
        assert!(read.iter().enumerate().all(|(i, b)| b[..] == vec![i as u8; 1000][..]));
        let each = store.get_each(few).unwrap();
        assert!(each.iter().all(|b| b.is_ok()));
        assert_eq!(store.get(&keys[0]).unwrap()[..], vec![0u8; 1000][..]);
    }
    assert_eq!(threads(), before, "reads of {READ_HERE} objects started threads");
    // One more object than that goes to the store's threads, which start with the call: the
    // count above would have seen them.
    let read = store.get_all(&keys).unwrap();
    assert_eq!(read.len(), READ_HERE + 1);
    assert!(
        threads() > before,
        "a read of {} objects started no thread",
        READ_HERE + 1
    );
}

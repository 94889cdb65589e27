//! The `microstereo` binary: parses the command line and reports errors with exit code 2.

fn main() {
    keep_freed_memory();
    std::process::exit(microstereo::cli::main());
}

/// Makes glibc keep freed memory for the next allocation instead of returning it to the
/// system. Every frame allocates the same multi-megabyte maps again (a 1280×1024 f32 map
/// is 5 MB); by default each one is a fresh `mmap`, and faulting its pages in took as
/// long as the median filter that fills it. The price: the process keeps its peak size.
fn keep_freed_memory() {
    #[cfg(all(target_os = "linux", target_env = "gnu"))]
    // SAFETY: mallopt only sets allocator parameters; called before any thread starts.
    unsafe {
        libc::mallopt(libc::M_MMAP_THRESHOLD, 1 << 30);
        libc::mallopt(libc::M_TRIM_THRESHOLD, 1 << 30);
    }
}

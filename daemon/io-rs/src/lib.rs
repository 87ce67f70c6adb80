//! keyframed-io: a small C ABI over the `mcap` and `zenoh` crates.
//!
//! Rules of the ABI (see daemon/output/io_ffi.h, the C declarations):
//! - Handles are opaque pointers, created by `*_open`/`*_declare` and released by
//!   exactly one `*_close`/`*_undeclare` call (NULL is accepted and ignored).
//! - Fallible calls return 0 on success and -1 on failure, writing a NUL-terminated,
//!   possibly truncated message into the caller's `err` buffer (which may be NULL).
//! - Pointer arguments are NULL (reported as an error) or valid for the call: strings
//!   NUL-terminated, arrays holding the stated count, handles from this crate and not
//!   yet released. Entry points that take pointers are therefore `unsafe`.
//! - No panic crosses the boundary: every entry point runs under `catch_unwind`
//!   and turns a panic into an error.

use std::collections::BTreeMap;
use std::ffi::{c_char, c_int, c_void, CStr};
use std::fs::File;
use std::io::{BufWriter, Seek, SeekFrom, Write};
use std::panic::{catch_unwind, AssertUnwindSafe};
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::mpsc::{sync_channel, Receiver, TrySendError};
use std::sync::{Arc, Mutex};
use std::thread::JoinHandle;

use zenoh::qos::{CongestionControl, Priority};
use zenoh::Wait;

type Res<T> = Result<T, String>;

/// Writes `msg` into the caller's buffer, truncated on a UTF-8 boundary, NUL-terminated.
fn set_error(err: *mut c_char, err_len: usize, msg: &str) {
    if err.is_null() || err_len == 0 {
        return;
    }
    let mut n = msg.len().min(err_len - 1);
    while n > 0 && !msg.is_char_boundary(n) {
        n -= 1;
    }
    // SAFETY: the caller promises `err` points to `err_len` writable bytes.
    unsafe {
        std::ptr::copy_nonoverlapping(msg.as_ptr(), err.cast::<u8>(), n);
        *err.add(n) = 0;
    }
}

/// An error with its causes: the `mcap` crate's I/O error says "I/O error from
/// writing, or reading a compression stream" and keeps the OS's reason (a full disk,
/// a read-only file system) in its source.
fn describe(e: &dyn std::error::Error) -> String {
    let mut text = e.to_string();
    let mut cause = e.source();
    while let Some(c) = cause {
        let more = c.to_string();
        if !text.ends_with(&more) {
            text += ": ";
            text += &more;
        }
        cause = c.source();
    }
    text
}

/// `text` without the places in Zenoh's sources its errors name, wherever they are
/// (" at /root/.cargo/…/endpoint.rs:615."; a nested error has one of its own).
fn without_source_locations(text: &str) -> String {
    let mut out = String::with_capacity(text.len());
    let mut rest = text;
    while let Some(i) = rest.find(" at /") {
        let tail = &rest[i + 4..];
        let end = tail
            .find(|c: char| c.is_whitespace() || c == '"')
            .unwrap_or(tail.len());
        let place = tail[..end].trim_end_matches('.');
        let is_source = place
            .rsplit_once(".rs:")
            .is_some_and(|(_, n)| !n.is_empty() && n.bytes().all(|b| b.is_ascii_digit()));
        if is_source {
            out.push_str(&rest[..i]);
            rest = &tail[end..];
        } else {
            out.push_str(&rest[..i + 5]);
            rest = &rest[i + 5..];
        }
    }
    out.push_str(rest);
    out
}

/// A zenoh configuration error on one line: a JSON5 syntax error comes as pest's
/// multi-line report (" --> 1:9", the line, a caret, "= expected ..."), a wrong value
/// as serde's Debug text, and both end with where in zenoh's source they were made.
fn zenoh_config_error(e: &dyn std::fmt::Display) -> String {
    let text = without_source_locations(&e.to_string());
    let (mut position, mut message) = (None, None);
    for line in text.lines().map(str::trim) {
        if let Some(p) = line.strip_prefix("--> ") {
            position = Some(p.to_owned());
        } else if let Some(m) = line.strip_prefix("= ") {
            message = Some(m.to_owned());
        }
    }
    if let (Some(p), Some(m)) = (position, message) {
        let (line, column) = p.split_once(':').unwrap_or((&p, "?"));
        return format!("line {line}, column {column}: {m}");
    }
    if let (Some(a), Some(b)) = (text.find("msg: \""), text.find("\", location")) {
        if a + 6 <= b {
            let m = &text[a + 6..b];
            let at = text
                .find("line: ")
                .map(|i| &text[i..])
                .and_then(|t| t.split_once(" }"))
                .map(|(t, _)| t.replace("line: ", "line ").replace("column: ", "column "));
            return match at {
                Some(at) => format!("{at}: {m}"),
                None => m.to_owned(),
            };
        }
    }
    text.split_whitespace().collect::<Vec<_>>().join(" ")
}

fn panic_message(p: Box<dyn std::any::Any + Send>) -> String {
    if let Some(s) = p.downcast_ref::<&str>() {
        format!("internal error (panic): {s}")
    } else if let Some(s) = p.downcast_ref::<String>() {
        format!("internal error (panic): {s}")
    } else {
        "internal error (panic)".to_string()
    }
}

/// Runs `f`, mapping an error or a panic to `fallback` plus a message in `err`.
fn guard<T>(err: *mut c_char, err_len: usize, fallback: T, f: impl FnOnce() -> Res<T>) -> T {
    match catch_unwind(AssertUnwindSafe(f)) {
        Ok(Ok(v)) => v,
        Ok(Err(e)) => {
            set_error(err, err_len, &e);
            fallback
        }
        Err(p) => {
            set_error(err, err_len, &panic_message(p));
            fallback
        }
    }
}

/// Runs `f` where no error can be reported (release functions): swallows panics.
fn guard_void(f: impl FnOnce()) {
    let _ = catch_unwind(AssertUnwindSafe(f));
}

fn status(r: Res<()>) -> Res<c_int> {
    r.map(|()| 0)
}

/// A NUL-terminated string argument; NULL is an error naming the argument.
fn cstr<'a>(p: *const c_char, what: &str) -> Res<&'a str> {
    if p.is_null() {
        return Err(format!("{what} is NULL"));
    }
    // SAFETY: the caller passes a NUL-terminated string that outlives the call.
    unsafe { CStr::from_ptr(p) }
        .to_str()
        .map_err(|_| format!("{what} is not valid UTF-8"))
}

fn opt_cstr<'a>(p: *const c_char, what: &str) -> Res<Option<&'a str>> {
    if p.is_null() {
        Ok(None)
    } else {
        cstr(p, what).map(Some)
    }
}

fn bytes<'a>(p: *const u8, len: usize, what: &str) -> Res<&'a [u8]> {
    if len == 0 {
        return Ok(&[]);
    }
    if p.is_null() {
        return Err(format!("{what} is NULL"));
    }
    // SAFETY: the caller passes `len` readable bytes that outlive the call.
    Ok(unsafe { std::slice::from_raw_parts(p, len) })
}

fn handle<'a, T>(p: *mut T, what: &str) -> Res<&'a T> {
    // SAFETY: non-null handles were made by Box::into_raw here and are still live.
    unsafe { p.as_ref() }.ok_or_else(|| format!("{what} handle is NULL"))
}

// ---------------------------------------------------------------------------------
// MCAP

/// A file shared with the MCAP writer, so that flush can also fsync it.
struct SharedFile(Arc<File>);

impl Write for SharedFile {
    fn write(&mut self, buf: &[u8]) -> std::io::Result<usize> {
        (&*self.0).write(buf)
    }
    fn flush(&mut self) -> std::io::Result<()> {
        (&*self.0).flush()
    }
}

impl Seek for SharedFile {
    fn seek(&mut self, pos: SeekFrom) -> std::io::Result<u64> {
        (&*self.0).seek(pos)
    }
}

type McapInner = mcap::Writer<BufWriter<SharedFile>>;

pub struct KfioMcap {
    // None once a write failed for good or the file was closed.
    writer: Mutex<Option<McapInner>>,
    file: Arc<File>,
    path: String,
}

impl KfioMcap {
    fn with<T>(&self, f: impl FnOnce(&mut McapInner) -> mcap::McapResult<T>) -> Res<T> {
        let mut guard = self
            .writer
            .lock()
            .map_err(|_| "MCAP writer lock poisoned")?;
        let w = guard
            .as_mut()
            .ok_or_else(|| format!("{}: writer is closed after an earlier error", self.path))?;
        match f(w) {
            Ok(v) => Ok(v),
            Err(e) => {
                // A failed chunk leaves the file in an unknown state: stop writing to it.
                let msg = format!("{}: {}", self.path, describe(&e));
                if matches!(e, mcap::McapError::Io(_)) {
                    // Dropping tries to finish the file once more and ignores errors.
                    drop(guard.take());
                }
                Err(msg)
            }
        }
    }
}

type McapStream = mcap::io::MessageReader<std::io::BufReader<File>>;

/// The messages of the MCAP file at `path` in file order, one chunk decompressed at a
/// time; an error when it does not start with MCAP's magic.
fn open_message_stream(path: &str) -> Res<McapStream> {
    use std::io::Read;
    let mut file = File::open(path).map_err(|e| format!("cannot read {path}: {e}"))?;
    let mut magic = [0u8; 8];
    if file.read_exact(&mut magic).is_err() || magic[..] != *mcap::MAGIC {
        return Err(format!("{path}: not an MCAP file (no MCAP magic)"));
    }
    file.seek(SeekFrom::Start(0))
        .map_err(|e| format!("cannot read {path}: {e}"))?;
    // A corrupt record length must be an error, not a huge allocation (which a Pi's
    // memory would refuse with an abort, in the repair of a flying daemon): no record
    // the recorder writes comes near 128 MiB, decompressed or not (chunks of 256 KiB,
    // or of one message: a keyframe of a few MB).
    let limit: usize = 128 << 20;
    // A chunk is checked against its CRC before any of its messages is given out: a
    // corrupt one ends the stream there (replay stops, a repair keeps what precedes
    // it) instead of passing on damaged messages, which a repair would sign afresh.
    let options = mcap::sans_io::LinearReaderOptions::default()
        .with_record_length_limit(limit)
        .with_prevalidate_chunk_crcs(true);
    Ok(mcap::io::MessageReader::new_with_options(
        std::io::BufReader::with_capacity(1 << 20, file),
        options,
    ))
}

/// "zstd", "lz4", or no compression ("none", "").
fn parse_compression(name: &str) -> Res<Option<mcap::Compression>> {
    match name {
        "zstd" => Ok(Some(mcap::Compression::Zstd)),
        "lz4" => Ok(Some(mcap::Compression::Lz4)),
        "" | "none" => Ok(None),
        other => Err(format!(
            "unknown MCAP compression '{other}' (zstd, lz4, none)"
        )),
    }
}

/// Messages of some topics of an MCAP file, streamed in file order (a replay source):
/// one chunk is decompressed at a time, so memory does not grow with the file.
pub struct KfioMcapReader {
    stream: McapStream,
    wanted: Vec<String>,
    current: Vec<u8>, // the data handed out by the last next()
    truncated: bool,
    done: bool,
}

/// Opens an MCAP file to stream the messages of `topics` (`count` NUL-terminated
/// names). A file cut short (SIGKILL, power cut) gives what precedes the cut and
/// reports itself truncated once read to the cut.
///
/// # Safety
/// Pointer arguments follow the ABI rules at the top of this file.
#[no_mangle]
pub unsafe extern "C" fn kfio_mcap_reader_open(
    path: *const c_char,
    topics: *const *const c_char,
    count: usize,
    err: *mut c_char,
    err_len: usize,
) -> *mut KfioMcapReader {
    guard(err, err_len, std::ptr::null_mut(), || {
        let path = cstr(path, "path")?;
        if count > 0 && topics.is_null() {
            return Err("topic array is NULL".into());
        }
        let mut wanted: Vec<String> = Vec::with_capacity(count);
        for i in 0..count {
            // SAFETY: the caller passes `count` string pointers.
            let t = unsafe { *topics.add(i) };
            wanted.push(cstr(t, "topic")?.to_string());
        }
        let stream = open_message_stream(path)?;
        Ok(Box::into_raw(Box::new(KfioMcapReader {
            stream,
            wanted,
            current: Vec::new(),
            truncated: false,
            done: false,
        })))
    })
}

/// The next message of the wanted topics: 1 with its topic index, log time and data
/// (valid until the next call or close), 0 at the end (or at a cut: see truncated).
///
/// # Safety
/// Pointer arguments follow the ABI rules at the top of this file.
#[no_mangle]
pub unsafe extern "C" fn kfio_mcap_reader_next(
    reader: *mut KfioMcapReader,
    topic: *mut u32,
    log_time: *mut u64,
    data: *mut *const u8,
    len: *mut usize,
) -> c_int {
    if reader.is_null() || topic.is_null() || log_time.is_null() || data.is_null() || len.is_null()
    {
        return 0;
    }
    let found = catch_unwind(AssertUnwindSafe(|| {
        // SAFETY: a live handle from kfio_mcap_reader_open.
        let r = unsafe { &mut *reader };
        while !r.done {
            match r.stream.next() {
                Some(Ok(m)) => {
                    if let Some(i) = r.wanted.iter().position(|t| *t == m.channel.topic) {
                        r.current = m.data.into_owned();
                        return Some((i as u32, m.log_time));
                    }
                }
                Some(Err(_)) => {
                    r.truncated = true;
                    r.done = true;
                }
                None => r.done = true,
            }
        }
        None
    }));
    let (t, time) = match found {
        Ok(Some(next)) => next,
        Ok(None) => return 0,
        Err(_) => {
            // A panic inside the reader (a corrupt file it did not expect): the record
            // ends here as a cut one, not as a complete one, and is not read further.
            // SAFETY: a live handle from kfio_mcap_reader_open.
            let r = unsafe { &mut *reader };
            r.truncated = true;
            r.done = true;
            return 0;
        }
    };
    // SAFETY: a live handle and valid out pointers.
    unsafe {
        let r = &*reader;
        *topic = t;
        *log_time = time;
        *data = r.current.as_ptr();
        *len = r.current.len();
    }
    1
}

/// 1 when the file ended before its end record (cut short), else 0.
///
/// # Safety
/// Pointer arguments follow the ABI rules at the top of this file.
#[no_mangle]
pub unsafe extern "C" fn kfio_mcap_reader_truncated(reader: *const KfioMcapReader) -> c_int {
    if reader.is_null() {
        return 0;
    }
    // SAFETY: a live handle.
    c_int::from(unsafe { &*reader }.truncated)
}

///
/// # Safety
/// Pointer arguments follow the ABI rules at the top of this file.
#[no_mangle]
pub unsafe extern "C" fn kfio_mcap_reader_close(reader: *mut KfioMcapReader) {
    guard_void(|| {
        if !reader.is_null() {
            // SAFETY: the handle came from Box::into_raw and is released once.
            drop(unsafe { Box::from_raw(reader) });
        }
    });
}

/// Opens an MCAP file for writing (truncating it). compression: "zstd", "lz4" or
/// "none"/""/NULL. chunk_size: target uncompressed chunk size in bytes (0: 64 KiB).
///
/// # Safety
/// Pointer arguments follow the ABI rules at the top of this file.
#[no_mangle]
pub unsafe extern "C" fn kfio_mcap_open(
    path: *const c_char,
    compression: *const c_char,
    chunk_size: u64,
    err: *mut c_char,
    err_len: usize,
) -> *mut KfioMcap {
    guard(err, err_len, std::ptr::null_mut(), || {
        let path = cstr(path, "path")?;
        let compression = parse_compression(opt_cstr(compression, "compression")?.unwrap_or(""))?;
        let file = Arc::new(File::create(path).map_err(|e| format!("cannot create {path}: {e}"))?);
        let chunk = if chunk_size == 0 {
            64 * 1024
        } else {
            chunk_size
        };
        let writer = mcap::WriteOptions::new()
            .compression(compression)
            .chunk_size(Some(chunk))
            // The daemon has few cores and other work: compress on the writer thread.
            .compression_threads(0)
            .library(concat!("keyframed-io ", env!("CARGO_PKG_VERSION")))
            .create(BufWriter::with_capacity(
                256 * 1024,
                SharedFile(Arc::clone(&file)),
            ))
            .map_err(|e| format!("cannot start MCAP file {path}: {}", describe(&e)))?;
        Ok(Box::into_raw(Box::new(KfioMcap {
            writer: Mutex::new(Some(writer)),
            file,
            path: path.to_string(),
        })))
    })
}

/// Adds a schema (returns its id in *id). encoding: "protobuf", "jsonschema", ...
///
/// # Safety
/// Pointer arguments follow the ABI rules at the top of this file.
#[no_mangle]
pub unsafe extern "C" fn kfio_mcap_add_schema(
    mcap: *mut KfioMcap,
    name: *const c_char,
    encoding: *const c_char,
    data: *const u8,
    len: usize,
    id: *mut u16,
    err: *mut c_char,
    err_len: usize,
) -> c_int {
    guard(err, err_len, -1, || {
        let m = handle(mcap, "MCAP")?;
        let name = cstr(name, "schema name")?;
        let encoding = cstr(encoding, "schema encoding")?;
        let data = bytes(data, len, "schema data")?;
        let sid = m.with(|w| w.add_schema(name, encoding, data))?;
        if !id.is_null() {
            // SAFETY: the caller passes a writable u16.
            unsafe { *id = sid };
        }
        Ok(0)
    })
}

/// Adds a channel on a schema (0: no schema); returns its id in *id. Metadata is
/// given as `count` key/value string pairs (arrays may be NULL when count is 0).
///
/// # Safety
/// Pointer arguments follow the ABI rules at the top of this file.
#[no_mangle]
pub unsafe extern "C" fn kfio_mcap_add_channel(
    mcap: *mut KfioMcap,
    schema_id: u16,
    topic: *const c_char,
    message_encoding: *const c_char,
    meta_keys: *const *const c_char,
    meta_values: *const *const c_char,
    meta_count: usize,
    id: *mut u16,
    err: *mut c_char,
    err_len: usize,
) -> c_int {
    guard(err, err_len, -1, || {
        let m = handle(mcap, "MCAP")?;
        let topic = cstr(topic, "topic")?;
        let encoding = cstr(message_encoding, "message encoding")?;
        let mut meta = BTreeMap::new();
        if meta_count > 0 {
            if meta_keys.is_null() || meta_values.is_null() {
                return Err("channel metadata arrays are NULL".into());
            }
            for i in 0..meta_count {
                // SAFETY: the caller passes `meta_count` pointers in each array.
                let (k, v) = unsafe { (*meta_keys.add(i), *meta_values.add(i)) };
                meta.insert(
                    cstr(k, "metadata key")?.to_string(),
                    cstr(v, "metadata value")?.to_string(),
                );
            }
        }
        let cid = m.with(|w| w.add_channel(schema_id, topic, encoding, &meta))?;
        if !id.is_null() {
            // SAFETY: the caller passes a writable u16.
            unsafe { *id = cid };
        }
        Ok(0)
    })
}

/// Writes one message. Times are nanoseconds (the recorder uses unix time).
///
/// # Safety
/// Pointer arguments follow the ABI rules at the top of this file.
#[no_mangle]
pub unsafe extern "C" fn kfio_mcap_write(
    mcap: *mut KfioMcap,
    channel_id: u16,
    sequence: u32,
    log_time: u64,
    publish_time: u64,
    data: *const u8,
    len: usize,
    err: *mut c_char,
    err_len: usize,
) -> c_int {
    guard(err, err_len, -1, || {
        let m = handle(mcap, "MCAP")?;
        let data = bytes(data, len, "message data")?;
        let header = mcap::records::MessageHeader {
            channel_id,
            sequence,
            log_time,
            publish_time,
        };
        status(m.with(|w| w.write_to_known_channel(&header, data)))
    })
}

/// Finishes the current chunk and writes it out, so that everything written so far
/// can be read back after a crash; with `sync` non-zero also fsyncs the file.
///
/// # Safety
/// Pointer arguments follow the ABI rules at the top of this file.
#[no_mangle]
pub unsafe extern "C" fn kfio_mcap_flush(
    mcap: *mut KfioMcap,
    sync: c_int,
    err: *mut c_char,
    err_len: usize,
) -> c_int {
    guard(err, err_len, -1, || {
        let m = handle(mcap, "MCAP")?;
        m.with(|w| w.flush())?;
        if sync != 0 {
            m.file
                .sync_data()
                .map_err(|e| format!("{}: fsync: {e}", m.path))?;
        }
        Ok(0)
    })
}

/// Writes the summary and footer, closes the file and releases the handle (also
/// on failure). NULL is accepted.
///
/// # Safety
/// Pointer arguments follow the ABI rules at the top of this file.
#[no_mangle]
pub unsafe extern "C" fn kfio_mcap_close(
    mcap: *mut KfioMcap,
    err: *mut c_char,
    err_len: usize,
) -> c_int {
    if mcap.is_null() {
        return 0;
    }
    // SAFETY: the handle was made by kfio_mcap_open and is released only here.
    let m = unsafe { Box::from_raw(mcap) };
    guard(err, err_len, -1, move || {
        let taken = m.writer.lock().ok().and_then(|mut g| g.take());
        let Some(mut w) = taken else {
            return Err(format!("{}: not finished after an earlier error", m.path));
        };
        let finished = w.finish().map(|_| ());
        let inner = w.into_inner();
        finished.map_err(|e| format!("{}: {}", m.path, describe(&e)))?;
        let shared = inner
            .into_inner()
            .map_err(|e| format!("{}: {}", m.path, e.error()))?;
        drop(shared);
        m.file
            .sync_data()
            .map_err(|e| format!("{}: fsync: {e}", m.path))?;
        Ok(0)
    })
}

/// The compression of the first chunk of an MCAP file ("" for none), found by
/// walking its records from the start (a file cut short has no summary to ask).
fn first_chunk_compression(path: &str) -> Option<String> {
    use std::io::Read;
    let mut f = std::io::BufReader::new(File::open(path).ok()?);
    let mut magic = [0u8; 8];
    f.read_exact(&mut magic).ok()?;
    for _ in 0..100_000 {
        let mut head = [0u8; 9];
        f.read_exact(&mut head).ok()?;
        let len = u64::from_le_bytes(head[1..9].try_into().ok()?);
        if head[0] == 0x06 {
            // Chunk: start and end time, uncompressed size (u64 each), CRC (u32), then
            // the compression as a u32-length string.
            let mut fixed = [0u8; 32];
            f.read_exact(&mut fixed).ok()?;
            let n = u32::from_le_bytes(fixed[28..32].try_into().ok()?) as usize;
            if n > 64 {
                return None;
            }
            let mut name = vec![0u8; n];
            f.read_exact(&mut name).ok()?;
            return String::from_utf8(name).ok();
        }
        f.seek_relative(i64::try_from(len).ok()?).ok()?;
    }
    None
}

/// Rewrites an MCAP file that was cut short (SIGKILL, a power cut: no summary, no
/// footer, perhaps half a chunk) as a complete file at `dst`: every message that
/// reads back, in file order, with its channel and schema, then the channels declared
/// before the cut that carried no message, chunked and compressed
/// as `compression` ("zstd", "lz4", "none"; "same": as the file's first chunk, zstd
/// without one), fsynced. *messages gets their count.
/// `dst` is created (truncated); the caller renames it into place. A non-zero
/// `*stop` (NULL: never), read between messages, ends it with an error.
///
/// # Safety
/// Pointer arguments follow the ABI rules at the top of this file.
#[no_mangle]
pub unsafe extern "C" fn kfio_mcap_recover(
    src: *const c_char,
    dst: *const c_char,
    compression: *const c_char,
    messages: *mut u64,
    stop: *const std::sync::atomic::AtomicI32,
    err: *mut c_char,
    err_len: usize,
) -> c_int {
    guard(err, err_len, -1, || {
        // SAFETY: NULL or a flag the caller keeps alive for the call.
        let stop = unsafe { stop.as_ref() };
        let src = cstr(src, "source")?;
        let dst = cstr(dst, "destination")?;
        let mut compression = opt_cstr(compression, "compression")?
            .unwrap_or("")
            .to_string();
        if compression == "same" {
            compression = first_chunk_compression(src).unwrap_or_else(|| "zstd".into());
        }
        let compression = parse_compression(&compression)?;
        // Not an MCAP file (nor the start of one): an error, and left as it is.
        let mut reader = open_message_stream(src)?;
        let file = Arc::new(File::create(dst).map_err(|e| format!("cannot create {dst}: {e}"))?);
        let mut writer = mcap::WriteOptions::new()
            .compression(compression)
            .chunk_size(Some(1 << 20))
            .compression_threads(0)
            .library(concat!(
                "keyframed-io ",
                env!("CARGO_PKG_VERSION"),
                " (recovered)"
            ))
            .create(BufWriter::with_capacity(
                1 << 20,
                SharedFile(Arc::clone(&file)),
            ))
            .map_err(|e| format!("cannot start MCAP file {dst}: {}", describe(&e)))?;
        let mut count: u64 = 0;
        for m in reader.by_ref() {
            // The first record that does not read is where the file was cut.
            let Ok(m) = m else { break };
            if stop.is_some_and(|s| s.load(std::sync::atomic::Ordering::Relaxed) != 0) {
                return Err(format!("{src}: recovery stopped"));
            }
            writer
                .write(&m)
                .map_err(|e| format!("{dst}: {}", describe(&e)))?;
            count += 1;
        }
        // Channels the file declared that carried no message before the cut (a topic
        // with nothing yet: no keyframe, no telemetry) are kept too, with their ids and
        // schemas, so that the repaired file lists what the recorder declared. Those
        // with messages are known to the writer already (the same content: no second
        // record). One that cannot be added (a conflicting id) is left out: the
        // messages are what a repair must not lose.
        for id in 0..=u16::MAX {
            let Some(channel) = reader.get_channel(id) else {
                continue;
            };
            let schema_id = match channel.schema.as_ref() {
                Some(s) => match writer.add_schema_with_id(s.id, &s.name, &s.encoding, &s.data) {
                    Ok(sid) => sid,
                    Err(_) => continue,
                },
                None => 0,
            };
            // Left out on an error, as above.
            let _ = writer.add_channel_with_id(
                id,
                schema_id,
                &channel.topic,
                &channel.message_encoding,
                &channel.metadata,
            );
        }
        writer
            .finish()
            .map_err(|e| format!("{dst}: {}", describe(&e)))?;
        writer
            .into_inner()
            .into_inner()
            .map_err(|e| format!("{dst}: {}", e.error()))?;
        file.sync_all().map_err(|e| format!("{dst}: fsync: {e}"))?;
        if !messages.is_null() {
            // SAFETY: a valid out pointer.
            unsafe { *messages = count };
        }
        Ok(0)
    })
}

// ---------------------------------------------------------------------------------
// Zenoh

pub struct KfioSession {
    session: zenoh::Session,
}

pub struct KfioPublisher {
    publisher: zenoh::pubsub::Publisher<'static>,
}

pub struct KfioQueryable {
    queryable: Option<zenoh::query::Queryable<()>>,
    worker: Option<JoinHandle<()>>,
    // Set at undeclare: queries still waiting are dropped unanswered, not served.
    stopping: Arc<AtomicBool>,
}

/// What a query callback answers with (valid only during the callback).
pub struct KfioReply<'a> {
    query: &'a zenoh::query::Query,
    replies: usize,
}

/// Called on the queryable's own thread (never on a zenoh runtime thread) with the
/// query's key expression and parameters (NUL-terminated); answers with
/// kfio_reply_ok / kfio_reply_err, any number of times, before returning.
pub type KfioQueryFn = Option<
    unsafe extern "C" fn(
        user: *mut c_void,
        key: *const c_char,
        parameters: *const c_char,
        reply: *mut KfioReply<'_>,
    ),
>;

/// Opens a session. The configuration comes from a JSON5 file (config_path), a JSON5
/// string (config_json5), or zenoh's defaults when both are NULL; then each
/// override `keys[i]` = `values[i]` (JSON5 values, e.g. "mode" = "\"peer\"",
/// "connect/endpoints" = "[\"tcp/127.0.0.1:7447\"]") is applied in order.
///
/// # Safety
/// Pointer arguments follow the ABI rules at the top of this file.
#[no_mangle]
pub unsafe extern "C" fn kfio_session_open(
    config_path: *const c_char,
    config_json5: *const c_char,
    keys: *const *const c_char,
    values: *const *const c_char,
    count: usize,
    err: *mut c_char,
    err_len: usize,
) -> *mut KfioSession {
    guard(err, err_len, std::ptr::null_mut(), || {
        let mut config = if let Some(path) = opt_cstr(config_path, "config path")? {
            load_config_file(path)?
        } else if let Some(text) = opt_cstr(config_json5, "config")? {
            let mut c = zenoh::Config::from_json5(text)
                .map_err(|e| format!("zenoh config: {}", zenoh_config_error(&e)))?;
            apply_link_defaults(&mut c)?;
            c
        } else {
            let mut c = zenoh::Config::default();
            apply_link_defaults(&mut c)?;
            c
        };
        if count > 0 && (keys.is_null() || values.is_null()) {
            return Err("config override arrays are NULL".into());
        }
        for i in 0..count {
            // SAFETY: the caller passes `count` pointers in each array.
            let (k, v) = unsafe { (*keys.add(i), *values.add(i)) };
            let k = cstr(k, "override key")?;
            let v = cstr(v, "override value")?;
            config
                .insert_json5(k, v)
                .map_err(|e| format!("zenoh config {k} = {v}: {e}"))?;
        }
        let session = zenoh::open(config)
            .wait()
            .map_err(|e| format!("cannot open zenoh session: {e}"))?;
        Ok(Box::into_raw(Box::new(KfioSession { session })))
    })
}

/// Reads a Zenoh JSON5 configuration file as kfio_session_open does, without opening
/// a session: 0 when zenoh takes it, else -1 with zenoh's reason in err.
///
/// # Safety
/// Pointer arguments follow the ABI rules at the top of this file.
#[no_mangle]
pub unsafe extern "C" fn kfio_zenoh_config_check(
    config_path: *const c_char,
    err: *mut c_char,
    err_len: usize,
) -> c_int {
    guard(err, err_len, -1, || {
        let path = cstr(config_path, "config path")?;
        load_config_file(path)?;
        Ok(0)
    })
}

/// One setting of the configuration a session opens with (`config_path` NULL: the
/// defaults), our defaults applied, as JSON into out: 0, or -1 with the reason in err.
///
/// # Safety
/// Pointer arguments follow the ABI rules at the top of this file.
#[no_mangle]
pub unsafe extern "C" fn kfio_zenoh_config_get(
    config_path: *const c_char,
    key: *const c_char,
    out: *mut c_char,
    out_len: usize,
    err: *mut c_char,
    err_len: usize,
) -> c_int {
    guard(err, err_len, -1, || {
        let config = match opt_cstr(config_path, "config path")? {
            Some(path) => load_config_file(path)?,
            None => {
                let mut c = zenoh::Config::default();
                apply_link_defaults(&mut c)?;
                c
            }
        };
        let key = cstr(key, "key")?;
        let value = config
            .get_json(key)
            .map_err(|e| format!("zenoh config {key}: {e}"))?;
        set_error(out, out_len, &value);
        Ok(0)
    })
}

/// A configuration file as zenoh reads it, with our defaults where it sets nothing.
fn load_config_file(path: &str) -> Res<zenoh::Config> {
    let mut config = zenoh::Config::from_file(path)
        .map_err(|e| format!("zenoh config {path}: {}", zenoh_config_error(&e)))?;
    apply_link_defaults(&mut config)?;
    Ok(config)
}

const WAIT_BEFORE_CLOSE: &str =
    "transport/link/tx/queue/congestion_control/block/wait_before_close";
/// Zenoh's own: 5 s.
const ZENOH_WAIT_BEFORE_CLOSE_US: &str = "5000000";
/// Ours: 60 s.
const KEYFRAMED_WAIT_BEFORE_CLOSE_US: &str = "60000000";

/// Keyframes are put reliably, blocking while the link is congested. Zenoh closes the
/// whole session when such a put finds no free batch (64 KB) for
/// block.wait_before_close, 5 s by default: on a radio link under about 13 kB/s every
/// keyframe would drop the session (status, preview and queries with it). Unless the
/// configuration sets another value, the wait is 60 s (a 64 KB batch at 1.1 kB/s).
fn apply_link_defaults(config: &mut zenoh::Config) -> Res<()> {
    let now = config
        .get_json(WAIT_BEFORE_CLOSE)
        .map_err(|e| format!("zenoh config {WAIT_BEFORE_CLOSE}: {e}"))?;
    if now == ZENOH_WAIT_BEFORE_CLOSE_US {
        config
            .insert_json5(WAIT_BEFORE_CLOSE, KEYFRAMED_WAIT_BEFORE_CLOSE_US)
            .map_err(|e| format!("zenoh config {WAIT_BEFORE_CLOSE}: {e}"))?;
    }
    Ok(())
}

/// Closes the session (publishers and queryables declared on it stop working) and
/// releases the handle. NULL is accepted.
///
/// # Safety
/// Pointer arguments follow the ABI rules at the top of this file.
#[no_mangle]
pub unsafe extern "C" fn kfio_session_close(session: *mut KfioSession) {
    if session.is_null() {
        return;
    }
    // SAFETY: made by kfio_session_open, released only here.
    let s = unsafe { Box::from_raw(session) };
    guard_void(move || {
        let _ = s.session.close().wait();
    });
}

/// The session's zenoh id as text (for logs).
///
/// # Safety
/// Pointer arguments follow the ABI rules at the top of this file.
#[no_mangle]
pub unsafe extern "C" fn kfio_session_zid(
    session: *mut KfioSession,
    out: *mut c_char,
    out_len: usize,
) -> c_int {
    guard(std::ptr::null_mut(), 0, -1, || {
        let s = handle(session, "session")?;
        set_error(out, out_len, &s.session.zid().to_string());
        Ok(0)
    })
}

pub const KFIO_PUB_RELIABLE: c_int = 0;
pub const KFIO_PUB_BEST_EFFORT: c_int = 1;

/// Declares a publisher. kind 0 (KFIO_PUB_RELIABLE): congestion control Block, data
/// priority: a put waits rather than drops (keyframes). kind 1 (KFIO_PUB_BEST_EFFORT):
/// congestion control Drop, lower priority (preview, status).
///
/// # Safety
/// Pointer arguments follow the ABI rules at the top of this file.
#[no_mangle]
pub unsafe extern "C" fn kfio_publisher_declare(
    session: *mut KfioSession,
    key: *const c_char,
    kind: c_int,
    err: *mut c_char,
    err_len: usize,
) -> *mut KfioPublisher {
    guard(err, err_len, std::ptr::null_mut(), || {
        let s = handle(session, "session")?;
        let key = cstr(key, "key expression")?.to_string();
        let (cc, prio) = match kind {
            KFIO_PUB_RELIABLE => (CongestionControl::Block, Priority::Data),
            KFIO_PUB_BEST_EFFORT => (CongestionControl::Drop, Priority::DataLow),
            k => return Err(format!("unknown publisher kind {k}")),
        };
        let publisher = s
            .session
            .declare_publisher(key.clone())
            .congestion_control(cc)
            .priority(prio)
            .wait()
            .map_err(|e| format!("cannot declare publisher on '{key}': {e}"))?;
        Ok(Box::into_raw(Box::new(KfioPublisher { publisher })))
    })
}

/// Publishes `data` with an optional attachment (att may be NULL when att_len is 0).
///
/// # Safety
/// Pointer arguments follow the ABI rules at the top of this file.
#[no_mangle]
pub unsafe extern "C" fn kfio_publisher_put(
    publisher: *mut KfioPublisher,
    data: *const u8,
    len: usize,
    att: *const u8,
    att_len: usize,
    err: *mut c_char,
    err_len: usize,
) -> c_int {
    guard(err, err_len, -1, || {
        let p = handle(publisher, "publisher")?;
        let data = bytes(data, len, "payload")?;
        let mut put = p.publisher.put(data.to_vec());
        if att_len > 0 {
            put = put.attachment(bytes(att, att_len, "attachment")?.to_vec());
        }
        status(
            put.wait()
                .map_err(|e| format!("put on '{}': {e}", p.publisher.key_expr())),
        )
    })
}

/// Undeclares the publisher and releases the handle. NULL is accepted.
///
/// # Safety
/// Pointer arguments follow the ABI rules at the top of this file.
#[no_mangle]
pub unsafe extern "C" fn kfio_publisher_undeclare(publisher: *mut KfioPublisher) {
    if publisher.is_null() {
        return;
    }
    // SAFETY: made by kfio_publisher_declare, released only here.
    let p = unsafe { Box::from_raw(publisher) };
    guard_void(move || {
        let _ = p.publisher.undeclare().wait();
    });
}

struct UserData(*mut c_void);
// SAFETY: the C caller promises the callback and its user data may be used from the
// queryable's thread (documented in io_ffi.h).
unsafe impl Send for UserData {}

fn serve_queries(
    rx: Receiver<zenoh::query::Query>,
    f: KfioQueryFn,
    user: UserData,
    stopping: Arc<AtomicBool>,
) {
    let Some(f) = f else { return };
    while let Ok(query) = rx.recv() {
        if stopping.load(Ordering::Acquire) {
            // Undeclared: the rest of the queue is dropped, and zenoh ends each of
            // those queries with no reply (the querier asks again elsewhere or later).
            continue;
        }
        let user = user.0;
        let _ = catch_unwind(AssertUnwindSafe(|| {
            let key = std::ffi::CString::new(query.key_expr().as_str()).unwrap_or_default();
            let params = std::ffi::CString::new(query.parameters().as_str()).unwrap_or_default();
            let mut reply = KfioReply {
                query: &query,
                replies: 0,
            };
            // SAFETY: the C callback receives pointers valid for the call's duration.
            unsafe { f(user, key.as_ptr(), params.as_ptr(), &mut reply) };
        }));
        // Dropping the query ends it: the querier gets what was replied, or nothing.
    }
}

/// Declares a queryable on `key` (wildcards allowed, e.g. "keyframed/uav1/keyframes/*").
/// Queries are answered one at a time on a thread of the queryable's own, so the
/// callback may block on disk I/O. At most 64 queries wait; more are dropped.
///
/// # Safety
/// Pointer arguments follow the ABI rules at the top of this file.
#[no_mangle]
pub unsafe extern "C" fn kfio_queryable_declare(
    session: *mut KfioSession,
    key: *const c_char,
    callback: KfioQueryFn,
    user: *mut c_void,
    err: *mut c_char,
    err_len: usize,
) -> *mut KfioQueryable {
    guard(err, err_len, std::ptr::null_mut(), || {
        let s = handle(session, "session")?;
        let key = cstr(key, "key expression")?.to_string();
        if callback.is_none() {
            return Err("query callback is NULL".into());
        }
        let (tx, rx) = sync_channel::<zenoh::query::Query>(64);
        let queryable = s
            .session
            .declare_queryable(key.clone())
            .callback(move |q| match tx.try_send(q) {
                Ok(()) | Err(TrySendError::Disconnected(_)) => {}
                // 64 queries waiting: this one is dropped, and zenoh ends it at once
                // with no reply; the ground station asks again for what is missing.
                Err(TrySendError::Full(_)) => {}
            })
            .wait()
            .map_err(|e| format!("cannot declare queryable on '{key}': {e}"))?;
        let user = UserData(user);
        let stopping = Arc::new(AtomicBool::new(false));
        let worker_stopping = Arc::clone(&stopping);
        let worker = std::thread::Builder::new()
            .name("kfio-queryable".into())
            .spawn(move || serve_queries(rx, callback, user, worker_stopping))
            .map_err(|e| format!("cannot start queryable thread: {e}"))?;
        Ok(Box::into_raw(Box::new(KfioQueryable {
            queryable: Some(queryable),
            worker: Some(worker),
            stopping,
        })))
    })
}

/// Undeclares the queryable, drops the queries still waiting (unanswered), waits for
/// a callback in progress to return, and releases the handle: the callback is not
/// called after this returns.
///
/// # Safety
/// Pointer arguments follow the ABI rules at the top of this file.
#[no_mangle]
pub unsafe extern "C" fn kfio_queryable_undeclare(queryable: *mut KfioQueryable) {
    if queryable.is_null() {
        return;
    }
    // SAFETY: made by kfio_queryable_declare, released only here.
    let mut q = unsafe { Box::from_raw(queryable) };
    guard_void(move || {
        q.stopping.store(true, Ordering::Release);
        if let Some(qq) = q.queryable.take() {
            // Undeclaring drops the callback and with it the channel's sender.
            let _ = qq.undeclare().wait();
        }
        if let Some(w) = q.worker.take() {
            let _ = w.join();
        }
    });
}

/// Replies to the query with `data` (and an optional attachment) on `key`, or on the
/// query's own key expression when `key` is NULL (only valid for a non-wildcard query).
///
/// # Safety
/// Pointer arguments follow the ABI rules at the top of this file.
#[no_mangle]
pub unsafe extern "C" fn kfio_reply_ok(
    reply: *mut KfioReply<'_>,
    key: *const c_char,
    data: *const u8,
    len: usize,
    att: *const u8,
    att_len: usize,
    err: *mut c_char,
    err_len: usize,
) -> c_int {
    guard(err, err_len, -1, || {
        // SAFETY: `reply` is the pointer handed to the callback, valid during it.
        let r = unsafe { reply.as_mut() }.ok_or("reply is NULL")?;
        let key = match opt_cstr(key, "reply key")? {
            Some(k) => k.to_string(),
            None => r.query.key_expr().as_str().to_string(),
        };
        let data = bytes(data, len, "reply payload")?.to_vec();
        let mut b = r.query.reply(key.clone(), data);
        if att_len > 0 {
            b = b.attachment(bytes(att, att_len, "reply attachment")?.to_vec());
        }
        b.wait().map_err(|e| format!("reply on '{key}': {e}"))?;
        r.replies += 1;
        Ok(0)
    })
}

/// Replies with an error message (for example "no such keyframe").
///
/// # Safety
/// Pointer arguments follow the ABI rules at the top of this file.
#[no_mangle]
pub unsafe extern "C" fn kfio_reply_err(
    reply: *mut KfioReply<'_>,
    message: *const c_char,
    err: *mut c_char,
    err_len: usize,
) -> c_int {
    guard(err, err_len, -1, || {
        // SAFETY: `reply` is the pointer handed to the callback, valid during it.
        let r = unsafe { reply.as_mut() }.ok_or("reply is NULL")?;
        let msg = cstr(message, "message")?.to_string();
        r.query
            .reply_err(msg.into_bytes())
            .wait()
            .map_err(|e| format!("error reply: {e}"))?;
        r.replies += 1;
        Ok(0)
    })
}

/// The crate's version and its zenoh/mcap versions, for --version output.
#[no_mangle]
pub extern "C" fn kfio_version() -> *const c_char {
    c"keyframed-io 0.1.0 (zenoh 1.10.2, mcap 0.26)".as_ptr()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn source_locations_leave_zenoh_errors() {
        let nested = "Json5Err(Message { msg: \"Endpoints must be of the form x: garbage at \
                      /r/.cargo/endpoint.rs:615.\", location: Some(Location { line: 1, \
                      column: 2 }) }) at /r/.cargo/config.rs:86.";
        assert_eq!(
            zenoh_config_error(&nested),
            "line 1, column 2: Endpoints must be of the form x: garbage"
        );
        assert_eq!(
            without_source_locations("at /etc/x.json5 at /a/b.rs:1"),
            "at /etc/x.json5"
        );
    }

    #[test]
    fn error_is_truncated_on_char_boundary() {
        let mut buf = [1 as c_char; 4];
        set_error(buf.as_mut_ptr(), buf.len(), "aéé");
        let s = unsafe { CStr::from_ptr(buf.as_ptr()) };
        assert_eq!(s.to_str().unwrap(), "aé");
    }
}

/* C declarations of the Rust I/O crate (daemon/io-rs/src/lib.rs).
 *
 * Handles are opaque and released by exactly one close/undeclare call (NULL is
 * ignored). Fallible calls return 0 on success and -1 on failure, writing a
 * NUL-terminated one-line message into `err` (err_len bytes; err may be NULL).
 * No Rust panic crosses this boundary: it becomes an error return.
 * An MCAP handle must be used by one thread at a time. */
#pragma once

#include <stddef.h>
#include <stdint.h>

#ifdef __cplusplus
extern "C" {
#endif

typedef struct KfioMcap kfio_mcap;
typedef struct KfioSession kfio_session;
typedef struct KfioPublisher kfio_publisher;
typedef struct KfioQueryable kfio_queryable;
typedef struct KfioReply kfio_reply;

/* ---- MCAP ---- */

/* compression: "zstd", "lz4", "none" (or NULL); chunk_size: bytes, 0 = 64 KiB. */
kfio_mcap* kfio_mcap_open(const char* path, const char* compression, uint64_t chunk_size, char* err,
                          size_t err_len);
int kfio_mcap_add_schema(kfio_mcap* mcap, const char* name, const char* encoding,
                         const uint8_t* data, size_t len, uint16_t* id, char* err, size_t err_len);
/* Channel metadata: meta_count key/value pairs (arrays may be NULL when 0). */
int kfio_mcap_add_channel(kfio_mcap* mcap, uint16_t schema_id, const char* topic,
                          const char* message_encoding, const char* const* meta_keys,
                          const char* const* meta_values, size_t meta_count, uint16_t* id,
                          char* err, size_t err_len);
int kfio_mcap_write(kfio_mcap* mcap, uint16_t channel_id, uint32_t sequence, uint64_t log_time,
                    uint64_t publish_time, const uint8_t* data, size_t len, char* err,
                    size_t err_len);
/* Finishes the current chunk and writes it out (sync != 0: also fsync). */
int kfio_mcap_flush(kfio_mcap* mcap, int sync, char* err, size_t err_len);
/* Writes summary and footer, closes the file, releases the handle (also on error). */
int kfio_mcap_close(kfio_mcap* mcap, char* err, size_t err_len);
/* Rewrites `src`, an MCAP file cut short, complete at `dst` (created): every message
 * that reads back, compressed as `compression` ("zstd", "lz4", "none"; "same": as
 * its first chunk), fsynced; *messages gets their count. A non-zero *stop (NULL:
 * never) ends it early, with an error. 0 on success. */
int kfio_mcap_recover(const char* src, const char* dst, const char* compression, uint64_t* messages,
                      const int32_t* stop, char* err, size_t err_len);

/* Reading (replay): the messages of `count` topics, streamed in file order (one chunk
 * in memory at a time). next() returns 1 with the topic's index in `topics`, the log
 * time and the data (valid until the next call or close), 0 at the end.
 * truncated(), once next() has returned 0: the file was cut short or is corrupt. */
typedef struct KfioMcapReader kfio_mcap_reader;
kfio_mcap_reader* kfio_mcap_reader_open(const char* path, const char* const* topics, size_t count,
                                        char* err, size_t err_len);
int kfio_mcap_reader_next(kfio_mcap_reader* reader, uint32_t* topic, uint64_t* log_time,
                          const uint8_t** data, size_t* len);
int kfio_mcap_reader_truncated(const kfio_mcap_reader* reader);
void kfio_mcap_reader_close(kfio_mcap_reader* reader);

/* ---- Zenoh ---- */

/* Configuration from a JSON5 file (config_path) or string (config_json5), or the
 * defaults when both are NULL; then keys[i] = values[i] (JSON5 values) applied. */
kfio_session* kfio_session_open(const char* config_path, const char* config_json5,
                                const char* const* keys, const char* const* values, size_t count,
                                char* err, size_t err_len);
void kfio_session_close(kfio_session* session);
/* Reads a JSON5 configuration file as kfio_session_open does, without opening a
 * session: 0 when zenoh takes it, -1 with the reason in err. */
int kfio_zenoh_config_check(const char* config_path, char* err, size_t err_len);
/* One setting ("transport/link/tx/...") of the configuration a session would open with
 * (config_path NULL: the defaults), keyframed's defaults applied, as JSON in out: 0, or
 * -1 with the reason in err. */
int kfio_zenoh_config_get(const char* config_path, const char* key, char* out, size_t out_len,
                          char* err, size_t err_len);
/* Writes the session's zenoh id (hex) into out. */
int kfio_session_zid(kfio_session* session, char* out, size_t out_len);

enum {
  KFIO_PUB_RELIABLE = 0,    /* congestion control Block, priority Data: never dropped */
  KFIO_PUB_BEST_EFFORT = 1, /* congestion control Drop, priority DataLow */
};
kfio_publisher* kfio_publisher_declare(kfio_session* session, const char* key, int kind, char* err,
                                       size_t err_len);
int kfio_publisher_put(kfio_publisher* publisher, const uint8_t* data, size_t len,
                       const uint8_t* attachment, size_t attachment_len, char* err, size_t err_len);
void kfio_publisher_undeclare(kfio_publisher* publisher);

/* Called on the queryable's own thread, one query at a time; key and parameters are
 * valid during the call. Answer with kfio_reply_ok/kfio_reply_err before returning;
 * a query left unanswered ends with no reply. */
typedef void (*kfio_query_fn)(void* user, const char* key, const char* parameters,
                              kfio_reply* reply);
kfio_queryable* kfio_queryable_declare(kfio_session* session, const char* key,
                                       kfio_query_fn callback, void* user, char* err,
                                       size_t err_len);
/* After this returns the callback is never called again. */
void kfio_queryable_undeclare(kfio_queryable* queryable);
/* key NULL: the query's own key expression (not valid for a wildcard query). */
int kfio_reply_ok(kfio_reply* reply, const char* key, const uint8_t* data, size_t len,
                  const uint8_t* attachment, size_t attachment_len, char* err, size_t err_len);
int kfio_reply_err(kfio_reply* reply, const char* message, char* err, size_t err_len);

const char* kfio_version(void);

#ifdef __cplusplus
}
#endif

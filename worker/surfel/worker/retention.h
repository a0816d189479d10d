#pragma once
/// \file
/// Disk quota and retention of blobs (issue 18.3, docs/retention.md).
///
/// What counts toward `--max-disk-gb`: every stored blob (uploaded clouds and job results, in
/// whichever BlobStore holds them) and the part files of unfinished uploads. Before bytes are
/// written (an upload's chunk, a job's result) they are reserved; when they would not fit, the
/// least recently used results and clouds are evicted until they do — never a cloud that a
/// queued or running job needs, never a part file. When even that cannot make room the write is
/// refused with kResourceExhausted (RESOURCE_EXHAUSTED), nothing is evicted, and the message
/// says how much is used, by what, and what is held by jobs.
///
/// "Last used" is a blob's store time, then each job read (JobManager::LoadCloud) and each
/// download of a result; it is kept in the store (table `blob_usage`, migration 6), so it
/// survives restarts and is shared by the processes of one PostgreSQL store. An evicted blob
/// leaves a tombstone per tenant (table `evictions`): a later GetCloud, Submit or download says
/// "evicted" and why, instead of "not found".
///
/// A time-to-live per tenant (`--ttl [TENANT=]DURATION`) removes the tenant's results and its
/// ownership of clouds that were not used for that long (Sweep, run periodically); a cloud's bytes
/// go with its last owner, never while a queued or running job needs it.
///
/// Thread-safe. One recursive mutex serialises reservations, evictions and sweeps; the server
/// also holds it (Lock) around Submit, DeleteCloud and an upload's final record, so that a cloud
/// is never evicted between "a job needs it" being checked and being recorded.

#include <cstdint>
#include <functional>
#include <map>
#include <mutex>
#include <optional>
#include <set>
#include <string>
#include <vector>

#include "surfel/v1/surfel.pb.h"
#include "surfel/worker/store.h"

namespace surfel::worker {

/// Limits of retention; all off by default.
struct RetentionOptions {
    /// Quota of blob bytes (stored blobs + upload part files); 0 = none.
    std::uint64_t max_disk_bytes = 0;
    /// Time-to-live of a tenant's results and cloud ownerships since their last use, ms; 0 = none.
    std::int64_t default_ttl_ms = 0;
    /// Per-tenant time-to-live overriding the default (0 = keep forever for that tenant).
    std::map<std::string, std::int64_t> tenant_ttl_ms;
    /// Time-to-live of an unfinished upload's part file since its last write, ms
    /// (`--upload-ttl`): an upload abandoned for longer must start again; 0 = keep part files
    /// until their upload finishes.
    std::int64_t upload_ttl_ms = kDefaultUploadTtlMs;
    /// One day: a resumable upload survives a night's interruption.
    static constexpr std::int64_t kDefaultUploadTtlMs = 24LL * 3600 * 1000;
};

/// Parses a duration: a number with a unit, "90s", "15m", "12h", "7d" (also "500ms"); "0" = none.
/// Throws kInvalidArgument naming `what` (the flag) and the text.
std::int64_t ParseDurationMs(const std::string& text, const std::string& what);

/// Formats milliseconds the way ParseDurationMs reads them, in the largest exact unit ("7d").
std::string FormatDurationMs(std::int64_t ms);

/// Applies one `--ttl` value: "DURATION" (everyone's default) or "TENANT=DURATION".
/// Throws kInvalidArgument.
void ApplyTtlFlag(const std::string& value, RetentionOptions* options);

/// The eviction policy, free of any store: from `lru` (least recently used first) the entries
/// whose key is not in `pinned`, in that order, until their sizes add up to at least `needed`.
/// Empty when `needed` is 0, or when all unpinned entries together are less than `needed` (then
/// nothing should be evicted at all).
std::vector<BlobUsage> ChooseVictims(const std::vector<BlobUsage>& lru,
                                     const std::set<std::string>& pinned, std::uint64_t needed);

/// The clouds that queued or running jobs of `store` need (JobKind::Inputs), each with the ids
/// of those jobs, oldest first.
std::map<std::string, std::vector<v1::Job>> CloudsInUse(const Store& store);

/// Called for every eviction: kind "cloud" or "result", cause "lru" or "ttl", bytes freed (0
/// when only a tenant's ownership of a shared cloud ended).
using EvictionHook =
    std::function<void(const std::string& kind, const std::string& cause, std::uint64_t bytes)>;

/// The quota and retention of one process's blobs (see the file comment).
class Retention {
  public:
    Retention(Store& store, RetentionOptions options, EvictionHook hook = {});

    /// Reconciles the usage table with what the blob store holds (a blob without an entry is
    /// recorded as used now; an entry without a blob is dropped) and counts the part files under
    /// `<data dir>/uploads`. Call once before serving.
    void Load();

    /// Reserves `bytes` about to be written for `what` ("upload u1", "result of job j…"),
    /// evicting least recently used blobs when they would not fit under the quota. Throws
    /// kResourceExhausted (nothing evicted) when they cannot fit, or at once when `whole` (the
    /// object's size with these bytes; an upload's grows chunk by chunk) exceeds the quota itself.
    void Reserve(std::uint64_t bytes, const std::string& what, std::uint64_t whole = 0);
    /// Gives back reserved bytes that were not written (or were removed: a discarded part file).
    void Release(std::uint64_t bytes);
    /// `reserved` bytes became the stored blob `key` of `size` bytes (used now); `reserved` is 0
    /// when none were reserved for it (then only the size is added).
    void Stored(const std::string& key, std::uint64_t size, std::uint64_t reserved);
    /// A blob was removed outside retention (DeleteCloud): its entry and bytes go.
    void Removed(const std::string& key);
    /// Marks a blob used now (a job read it, a client downloads it).
    void Touch(const std::string& key);

    /// Applies the time-to-lives at `now_ms`: returns how many results and cloud ownerships
    /// ended. Also re-reads the usage table (other processes of a shared store change it).
    std::size_t Sweep(std::int64_t now_ms);

    /// Removes the part files of unfinished uploads (`<data dir>/uploads/<id>.part`) that were
    /// not written to for longer than RetentionOptions::upload_ttl_ms at `now_ms`, giving back
    /// their bytes. Each is removed only while `claim(id)` holds its upload id (false: an upload
    /// call has it, and it is kept), then `release(id)`; an upload of that id afterwards starts
    /// from byte 0. Returns how many part files went; 0 when upload_ttl_ms is 0.
    std::size_t SweepUploads(std::int64_t now_ms,
                             const std::function<bool(const std::string& id)>& claim,
                             const std::function<void(const std::string& id)>& release);

    /// The message for a blob that is gone because it was evicted for `tenant` (any tenant when
    /// null): "<what> was evicted at <UTC time> (<reason>)"; nullopt when it was not evicted.
    std::optional<std::string> EvictedMessage(const std::string& key, const std::string& what,
                                              const std::string* tenant) const;

    /// Bytes of stored blobs.
    std::uint64_t stored_bytes() const;
    /// Bytes reserved: part files of uploads and results being written.
    std::uint64_t reserved_bytes() const;
    /// The quota (0 = none).
    std::uint64_t max_bytes() const { return options_.max_disk_bytes; }
    const RetentionOptions& options() const { return options_; }

    /// Holds evictions off while the caller checks and records what needs a cloud.
    std::unique_lock<std::recursive_mutex> Lock() const {
        return std::unique_lock<std::recursive_mutex>(mutex_);
    }

  private:
    /// The time-to-live of `tenant` (0 = none).
    std::int64_t TtlOf(const std::string& tenant) const;
    /// Evicts one blob for `reason`; returns the bytes freed. Lock held.
    std::uint64_t Evict(const BlobUsage& blob, const std::string& cause, const std::string& reason);
    /// Re-reads the table into stored_. Lock held.
    std::vector<BlobUsage> Refresh();

    Store& store_;
    RetentionOptions options_;
    EvictionHook hook_;
    mutable std::recursive_mutex mutex_;
    std::uint64_t stored_ = 0;
    std::uint64_t reserved_ = 0;
};

}  // namespace surfel::worker

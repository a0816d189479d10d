// Disk quota and retention of blobs: the LRU policy, time-to-lives, tombstones.
#include "surfel/worker/retention.h"

#include <spdlog/spdlog.h>
#include <sys/stat.h>

#include <algorithm>
#include <cctype>
#include <ctime>
#include <filesystem>

#include "surfel/base/error.h"
#include "surfel/worker/blob_store.h"
#include "surfel/worker/job_kind.h"

namespace surfel::worker {
namespace fs = std::filesystem;

// ---- durations

std::int64_t ParseDurationMs(const std::string& text, const std::string& what) {
    const auto bad = [&] {
        return Error(
            ErrorCode::kInvalidArgument,
            what + ": '" + text + "' is not a duration (e.g. 90s, 15m, 12h, 7d; 0 = none)");
    };
    if (text == "0") return 0;
    std::size_t digits = 0;
    while (digits < text.size() && std::isdigit(static_cast<unsigned char>(text[digits]))) ++digits;
    if (digits == 0 || digits > 12) throw bad();
    const std::int64_t n = std::stoll(text.substr(0, digits));
    const std::string unit = text.substr(digits);
    std::int64_t scale = 0;
    if (unit == "ms")
        scale = 1;
    else if (unit == "s")
        scale = 1000;
    else if (unit == "m")
        scale = 60'000;
    else if (unit == "h")
        scale = 3'600'000;
    else if (unit == "d")
        scale = 86'400'000;
    else
        throw bad();
    return n * scale;
}

std::string FormatDurationMs(std::int64_t ms) {
    if (ms == 0) return "0";
    for (const auto& [unit, scale] :
         {std::pair{"d", 86'400'000LL}, {"h", 3'600'000LL}, {"m", 60'000LL}, {"s", 1000LL}})
        if (ms % scale == 0) return std::to_string(ms / scale) + unit;
    return std::to_string(ms) + "ms";
}

void ApplyTtlFlag(const std::string& value, RetentionOptions* options) {
    const auto eq = value.find('=');
    if (eq == std::string::npos) {
        options->default_ttl_ms = ParseDurationMs(value, "--ttl");
        return;
    }
    const std::string tenant = value.substr(0, eq);
    if (tenant.empty())
        throw Error(ErrorCode::kInvalidArgument,
                    "--ttl " + value + ": expected TENANT=DURATION or DURATION");
    options->tenant_ttl_ms[tenant] = ParseDurationMs(value.substr(eq + 1), "--ttl " + tenant);
}

// ---- the policy

std::vector<BlobUsage> ChooseVictims(const std::vector<BlobUsage>& lru,
                                     const std::set<std::string>& pinned, std::uint64_t needed) {
    std::vector<BlobUsage> victims;
    if (needed == 0) return victims;
    std::uint64_t freed = 0;
    for (const BlobUsage& b : lru) {
        if (pinned.count(b.key)) continue;
        victims.push_back(b);
        freed += b.size;
        if (freed >= needed) return victims;
    }
    return {};  // not enough even with every unpinned blob: evict nothing
}

std::map<std::string, std::vector<v1::Job>> CloudsInUse(const Store& store) {
    std::map<std::string, std::vector<v1::Job>> in_use;
    for (const v1::Job& job : store.Unfinished()) {
        try {
            for (const CloudInput& input : KindOf(job.spec()).Inputs(job.spec()))
                in_use[input.id].push_back(job);
        } catch (const Error&) {  // a record this build cannot read: it pins nothing it names
        }
    }
    return in_use;
}

// ---- Retention

namespace {

std::string Utc(std::int64_t ms) {
    const std::time_t t = static_cast<std::time_t>(ms / 1000);
    std::tm tm{};
    gmtime_r(&t, &tm);
    char buf[32];
    std::strftime(buf, sizeof buf, "%Y-%m-%dT%H:%M:%SZ", &tm);
    return buf;
}

std::string Gb(std::uint64_t bytes) {
    char buf[64];
    std::snprintf(buf, sizeof buf, "%.3g GB (%llu bytes)", static_cast<double>(bytes) / 1e9,
                  static_cast<unsigned long long>(bytes));
    return buf;
}

bool IsCloudKey(const std::string& key) { return key.rfind("clouds/", 0) == 0; }
bool IsResultKey(const std::string& key) { return key.rfind("results/", 0) == 0; }

}  // namespace

Retention::Retention(Store& store, RetentionOptions options, EvictionHook hook)
    : store_(store), options_(std::move(options)), hook_(std::move(hook)) {}

std::int64_t Retention::TtlOf(const std::string& tenant) const {
    if (auto it = options_.tenant_ttl_ms.find(tenant); it != options_.tenant_ttl_ms.end())
        return it->second;
    return options_.default_ttl_ms;
}

void Retention::Load() {
    std::lock_guard lock(mutex_);
    std::map<std::string, std::uint64_t> blobs;
    for (auto& [key, size] : store_.blobs().List()) blobs[key] = size;
    std::size_t adopted = 0, dropped = 0;
    std::set<std::string> recorded;
    for (const BlobUsage& u : store_.ListBlobUsage()) {
        recorded.insert(u.key);
        if (!blobs.count(u.key)) {
            store_.RemoveBlobUsage(u.key);
            ++dropped;
        }
    }
    const std::int64_t now = NowUnixMs();
    for (const auto& [key, size] : blobs)
        if (!recorded.count(key)) {
            store_.PutBlobUsage(key, size, now);
            ++adopted;
        }
    Refresh();
    reserved_ = 0;
    std::error_code ec;
    if (!store_.data_dir().empty())
        for (fs::directory_iterator it(store_.data_dir() + "/uploads", ec), end; !ec && it != end;
             it.increment(ec)) {
            std::error_code sec;
            if (it->is_regular_file(sec)) reserved_ += it->file_size(sec);
        }
    spdlog::info("retention: {} blobs, {} stored, {} in upload part files{}{}{}", blobs.size(),
                 Gb(stored_), Gb(reserved_),
                 options_.max_disk_bytes ? ", quota " + Gb(options_.max_disk_bytes) : "",
                 adopted ? ", " + std::to_string(adopted) + " blobs adopted" : "",
                 dropped ? ", " + std::to_string(dropped) + " stale entries dropped" : "");
}

std::vector<BlobUsage> Retention::Refresh() {
    std::vector<BlobUsage> lru = store_.ListBlobUsage();
    stored_ = 0;
    for (const BlobUsage& u : lru) stored_ += u.size;
    return lru;
}

void Retention::Reserve(std::uint64_t bytes, const std::string& what, std::uint64_t whole) {
    std::lock_guard lock(mutex_);
    const std::uint64_t max = options_.max_disk_bytes;
    if (max != 0 && std::max(whole, bytes) > max)
        throw Error(ErrorCode::kResourceExhausted,
                    what + ": " + std::to_string(std::max(whole, bytes)) +
                        " bytes are more than the whole --max-disk-gb " + Gb(max));
    if (max == 0 || stored_ + reserved_ + bytes <= max) {
        reserved_ += bytes;
        return;
    }
    // Over the quota: the table is the truth (other processes of a shared store write it too).
    std::vector<BlobUsage> lru = Refresh();
    if (stored_ + reserved_ + bytes > max) {
        const std::uint64_t needed = stored_ + reserved_ + bytes - max;
        std::set<std::string> pinned;
        std::uint64_t pinned_bytes = 0;
        const auto in_use = CloudsInUse(store_);
        for (const BlobUsage& u : lru)
            if (IsCloudKey(u.key) && in_use.count(u.key.substr(7))) {
                pinned.insert(u.key);
                pinned_bytes += u.size;
            }
        const std::vector<BlobUsage> victims = ChooseVictims(lru, pinned, needed);
        if (victims.empty()) {
            throw Error(ErrorCode::kResourceExhausted,
                        what + ": " + std::to_string(bytes) +
                            " more bytes do not fit under --max-disk-gb " + Gb(max) + ": " +
                            Gb(stored_) + " in stored blobs (" + Gb(pinned_bytes) +
                            " of them clouds that queued or running jobs need, which are never "
                            "evicted) and " +
                            Gb(reserved_) +
                            " in uploads in progress and results being written; retry "
                            "after jobs finish or delete clouds");
        }
        const std::string reason =
            "least recently used, evicted to make room under --max-disk-gb " + Gb(max);
        for (const BlobUsage& v : victims) Evict(v, "lru", reason);
    }
    reserved_ += bytes;
}

void Retention::Release(std::uint64_t bytes) {
    std::lock_guard lock(mutex_);
    reserved_ -= std::min(bytes, reserved_);
}

void Retention::Stored(const std::string& key, std::uint64_t size, std::uint64_t reserved) {
    std::lock_guard lock(mutex_);
    reserved_ -= std::min(reserved, reserved_);
    store_.PutBlobUsage(key, size, NowUnixMs());
    Refresh();
}

void Retention::Removed(const std::string& key) {
    std::lock_guard lock(mutex_);
    if (store_.RemoveBlobUsage(key)) Refresh();
}

void Retention::Touch(const std::string& key) {
    try {
        store_.TouchBlobUsage(key, NowUnixMs());
    } catch (const Error& e) {  // best effort: a missed touch only ages the blob
        spdlog::warn("retention: cannot mark {} used: {}", key, e.what());
    }
}

std::uint64_t Retention::Evict(const BlobUsage& blob, const std::string& cause,
                               const std::string& reason) {
    const Eviction tomb{reason, NowUnixMs()};
    std::string kind;
    if (IsResultKey(blob.key)) {
        kind = "result";
        const std::optional<v1::Job> job = store_.FindJob(blob.key.substr(8));
        store_.PutEviction(blob.key, job ? job->tenant() : "", tomb);
        store_.blobs().Remove(blob.key);
    } else if (IsCloudKey(blob.key)) {
        kind = "cloud";
        const std::string id = blob.key.substr(7);
        std::vector<std::string> owners = store_.CloudOwners(id);
        if (owners.empty()) owners.push_back("");
        for (const std::string& owner : owners) store_.PutEviction(blob.key, owner, tomb);
        store_.DeleteCloud(id);  // record, ownerships and bytes
    } else {
        kind = "other";
        store_.blobs().Remove(blob.key);
    }
    store_.RemoveBlobUsage(blob.key);
    stored_ -= std::min(blob.size, stored_);
    spdlog::info("retention: evicted {} ({} bytes, last used {}): {}", blob.key, blob.size,
                 Utc(blob.last_used_ms), reason);
    if (hook_) hook_(kind, cause, blob.size);
    return blob.size;
}

std::size_t Retention::Sweep(std::int64_t now_ms) {
    std::lock_guard lock(mutex_);
    std::vector<BlobUsage> lru = Refresh();
    const bool any_ttl = options_.default_ttl_ms > 0 ||
                         std::any_of(options_.tenant_ttl_ms.begin(), options_.tenant_ttl_ms.end(),
                                     [](const auto& t) { return t.second > 0; });
    if (!any_ttl) return 0;
    const auto in_use = CloudsInUse(store_);
    const auto expired = [&](const std::string& tenant, const BlobUsage& u) {
        const std::int64_t ttl = TtlOf(tenant);
        return ttl > 0 && now_ms - u.last_used_ms > ttl;
    };
    const auto reason_for = [&](const std::string& tenant) {
        return "unused for longer than the time-to-live " + FormatDurationMs(TtlOf(tenant)) +
               " of tenant '" + tenant + "'";
    };
    std::size_t ended = 0;
    for (const BlobUsage& u : lru) {
        if (IsResultKey(u.key)) {
            const std::optional<v1::Job> job = store_.FindJob(u.key.substr(8));
            const std::string tenant = job ? job->tenant() : "";
            if (!expired(tenant, u)) continue;
            Evict(u, "ttl", reason_for(tenant));
            ++ended;
        } else if (IsCloudKey(u.key)) {
            const std::string id = u.key.substr(7);
            if (in_use.count(id)) continue;  // never while a queued or running job needs it
            const std::vector<std::string> owners = store_.CloudOwners(id);
            std::vector<std::string> ending;
            for (const std::string& o : owners)
                if (expired(o, u)) ending.push_back(o);
            if (ending.empty()) continue;
            if (ending.size() == owners.size()) {  // the last owners: the bytes go
                BlobUsage copy = u;
                const std::string reason = reason_for(ending.front());
                // One tombstone per owner, each with its own tenant's reason.
                for (const std::string& o : ending)
                    store_.PutEviction(u.key, o, Eviction{reason_for(o), NowUnixMs()});
                store_.DeleteCloud(id);
                store_.RemoveBlobUsage(u.key);
                stored_ -= std::min(u.size, stored_);
                spdlog::info("retention: evicted {} ({} bytes): {}", u.key, u.size, reason);
                if (hook_) hook_("cloud", "ttl", u.size);
            } else {
                for (const std::string& o : ending) {
                    store_.RemoveCloudOwner(o, id, nullptr);
                    store_.PutEviction(u.key, o, Eviction{reason_for(o), NowUnixMs()});
                    spdlog::info("retention: tenant '{}' no longer owns cloud {}: {}", o, id,
                                 reason_for(o));
                    if (hook_) hook_("cloud", "ttl", 0);
                }
            }
            ended += ending.size();
        }
    }
    return ended;
}

std::size_t Retention::SweepUploads(std::int64_t now_ms,
                                    const std::function<bool(const std::string& id)>& claim,
                                    const std::function<void(const std::string& id)>& release) {
    const std::int64_t ttl = options_.upload_ttl_ms;
    if (ttl <= 0 || store_.data_dir().empty()) return 0;
    // The last write of a part file, Unix ms (nullopt: gone).
    const auto last_write_ms = [](const std::string& path) -> std::optional<std::int64_t> {
        struct stat st {};
        if (::stat(path.c_str(), &st) != 0) return std::nullopt;
        return static_cast<std::int64_t>(st.st_mtim.tv_sec) * 1000 + st.st_mtim.tv_nsec / 1000000;
    };
    std::vector<std::string> stale;
    std::error_code ec;
    for (fs::directory_iterator it(store_.data_dir() + "/uploads", ec), end; !ec && it != end;
         it.increment(ec)) {
        const std::string name = it->path().filename().string();
        if (!name.ends_with(".part") || name.size() == 5) continue;
        const std::optional<std::int64_t> t = last_write_ms(it->path().string());
        if (t && now_ms - *t > ttl) stale.push_back(name.substr(0, name.size() - 5));
    }
    std::size_t removed = 0;
    for (const std::string& id : stale) {
        if (!claim(id)) continue;  // an upload call is writing it
        const std::string path = store_.UploadPath(id);
        // Checked again under the claim: a call may have written to it since the listing.
        const std::optional<std::int64_t> t = last_write_ms(path);
        std::error_code sec;
        const std::uint64_t size = t ? fs::file_size(path, sec) : 0;
        if (t && now_ms - *t > ttl && !sec && fs::remove(path, sec)) {
            Release(size);
            spdlog::info("retention: removed the part file of upload {} ({} bytes): not written to "
                         "for longer than --upload-ttl {}",
                         id, size, FormatDurationMs(ttl));
            if (hook_) hook_("upload", "ttl", size);
            ++removed;
        }
        release(id);
    }
    return removed;
}

std::optional<std::string> Retention::EvictedMessage(const std::string& key,
                                                     const std::string& what,
                                                     const std::string* tenant) const {
    const std::optional<Eviction> e = store_.FindEviction(key, tenant);
    if (!e) return std::nullopt;
    return what + " was evicted at " + Utc(e->evicted_ms) + " (" + e->reason + ")";
}

std::uint64_t Retention::stored_bytes() const {
    std::lock_guard lock(mutex_);
    return stored_;
}

std::uint64_t Retention::reserved_bytes() const {
    std::lock_guard lock(mutex_);
    return reserved_;
}

}  // namespace surfel::worker

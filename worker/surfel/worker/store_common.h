#pragma once
/// \file
/// What the store backends share beyond the interface: the record changes of the queue (so both
/// backends write the same jobs) and the check of a database's schema version. Internal to
/// worker/; not part of the store's API.

#include <cstdint>
#include <string>

#include "surfel/v1/surfel.pb.h"

namespace surfel::worker::store_detail {

/// The record of a job just claimed: RUNNING, started now, no progress yet.
v1::Job ClaimedRecord(v1::Job job, std::int64_t now_unix_ms);

/// The record of a job whose lease expired on attempt `attempts` (1-based, already counted):
/// QUEUED again while attempts < max_attempts, else FAILED (UNAVAILABLE) with
/// LeaseExhaustedMessage.
v1::Job ExpiredRecord(v1::Job job, int attempts, int max_attempts, const std::string& last_owner,
                      std::int64_t now_unix_ms);

/// Throws kFailedPrecondition when a database's schema (its highest applied migration) is newer
/// than this program knows: a newer release migrated it, and this one must not write to it.
void CheckSchemaNotNewer(std::int64_t applied_version, const std::string& where);

/// Throws kInvalidArgument unless lease_ms > 0 and the owner is not empty.
void CheckLease(const std::string& owner, std::int64_t lease_ms);

/// The record of a QUEUED job cancelled by RequestCancel.
v1::Job CancelledWhileQueuedRecord(v1::Job job, std::int64_t now_unix_ms);

/// Throws kInvalidArgument unless max_attempts >= 1.
void CheckMaxAttempts(int max_attempts);

}  // namespace surfel::worker::store_detail

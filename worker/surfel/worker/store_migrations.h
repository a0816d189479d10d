#pragma once
/// \file
/// The one schema of the stores, as an ordered list of versioned migrations, each written in
/// both dialects side by side (SQLite, PostgreSQL). A store applies, at open, every migration
/// whose version is missing from its `schema_migrations` table, each in its own transaction
/// together with the row that records it, so opening twice (or several processes opening at
/// once) changes nothing the second time.
///
/// Adding a migration is appending an entry; an applied entry is never edited.

#include <span>

namespace surfel::worker {

/// One step of the schema.
struct Migration {
    int version;           ///< 1, 2, ...: strictly increasing, never reused.
    const char* name;      ///< What it does, recorded in schema_migrations.
    const char* sqlite;    ///< SQLite statements (one script, ';'-separated).
    const char* postgres;  ///< PostgreSQL statements (one script, ';'-separated).
};

/// All migrations, in version order.
std::span<const Migration> Migrations();

/// The table that records the applied versions (same text in both dialects).
inline constexpr const char* kSchemaMigrationsTable =
    "CREATE TABLE IF NOT EXISTS schema_migrations (version INTEGER PRIMARY KEY, "
    "name TEXT NOT NULL, applied_ms BIGINT NOT NULL)";

}  // namespace surfel::worker

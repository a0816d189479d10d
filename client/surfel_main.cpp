// surfel: the command-line tool. Every job is a subcommand that runs in-process or, with
// --server host:port, on a surfel-server.
#include <iostream>

#include "cli_common.h"
#include "surfel/base/error.h"
#include "surfel/worker/job_kind.h"

int main(int argc, char** argv) {
    using namespace surfel::cli;
    CLI::App app{"surfel: point-cloud processing from the point-based graphics literature.\n"
                 "Reads PLY (ascii/binary) and XYZ; writes PLY, XYZ, EXR and PNG."};
    app.require_subcommand(1);
    app.set_version_flag("--version", "surfel 0.1.0");
    app.footer("Exit codes: 0 success, 2 usage error, 1 failure (the message is on stderr).\n"
               "Every job subcommand takes --json and then prints one JSON object with at least\n"
               "`points` and `time_ms` (the algorithm alone, file I/O excluded).\n"
               "Jobs (" + surfel::worker::JobKindNames() +
               ") run in-process, or on a surfel-server with --server host:port\n"
               "(or SURFEL_SERVER=host:port); upload, jobs, job, cancel and download talk to a server.\n"
               "Run `surfel <command> --help` for a command's options and an example.");
    RegisterIoCommands(app);
    RegisterSurfaceCommands(app);
    RegisterRenderCommands(app);
    RegisterSimplifyCommands(app);
    RegisterResampleCommands(app);
    RegisterBooleanCommands(app);
    RegisterServiceCommands(app);
    // An unknown command word: name it (CLI11 would only say that a subcommand is required).
    if (argc > 1 && argv[1][0] != '-') {
        std::string commands;
        bool known = false;
        for (const CLI::App* sub : app.get_subcommands({})) {
            known = known || sub->get_name() == argv[1];
            commands += (commands.empty() ? "" : ", ") + sub->get_name();
        }
        if (!known) {
            std::cerr << "surfel: unknown command '" << argv[1] << "' (commands: " << commands << ")\n"
                      << "Run `surfel --help` for what each does.\n";
            return kExitUsage;
        }
    }
    try {
        app.parse(argc, argv);
    } catch (const CLI::ParseError& e) {
        const int rc = app.exit(e);
        return rc == 0 ? kExitOk : kExitUsage;
    } catch (const UsageError& e) {
        std::cerr << "surfel: " << e.what() << "\n";
        return kExitUsage;
    } catch (const surfel::Error& e) {
        std::cerr << "surfel: error: " << e.what() << "\n";
        return kExitFailure;
    } catch (const std::exception& e) {
        std::cerr << "surfel: error: " << e.what() << "\n";
        return kExitFailure;
    }
    return kExitOk;
}

// brainshift: the command-line client of brainshiftd, plus the offline
// commands (register, phantom) that run the engine in this process.
// Built twice: brainshift-offline with the offline commands, and brainshift
// without the engine, which hands register and phantom to brainshift-offline
// (offline_forwarding.h: the per-scan `brainshift push` starts in ms).
#include <iostream>

#include <CLI/CLI.hpp>

#include "exit_codes.h"
#include "network_commands.h"
#ifdef BRAINSHIFT_HAVE_OFFLINE_COMMANDS
#include "offline_commands.h"
#include "format_conversion.h"
#else
#include "offline_forwarding.h"
#endif

int main(int argc, char** argv) {
#ifndef BRAINSHIFT_HAVE_OFFLINE_COMMANDS
  // NRRD output (pull --format nrrd) and a push of a DICOM series (DCMTK) or
  // of NRRD files need the engine's image readers and writers: those run in
  // brainshift-offline.
  if (brainshift::cli::is_nrrd_pull(argc, argv) || brainshift::cli::is_converting_push(argc, argv))
    return brainshift::cli::exec_offline(argc, argv);
#endif
  CLI::App app{"brainshift: client of the brainshiftd registration daemon"};
  app.footer(brainshift::cli::kExitCodesHelp);
  app.require_subcommand(1);
  brainshift::cli::NetworkOptions options;
  app.add_option("--server", options.server, "request endpoint of brainshiftd")->capture_default_str();
  app.add_option("--events", options.events, "event endpoint of brainshiftd")->capture_default_str();
  app.add_option("--timeout", options.timeout_s, "seconds to wait for each reply")
      ->capture_default_str()
      ->check(CLI::PositiveNumber);
  app.add_option("--key", options.key_prefix,
                 "CURVE: this client's key pair PREFIX (PREFIX.key, PREFIX.key_secret from brainshift keygen)")
      ->envname("BRAINSHIFT_KEY");
  app.add_option("--server-key", options.server_key_file, "CURVE: the server's public key file")
      ->envname("BRAINSHIFT_SERVER_KEY");
#ifdef BRAINSHIFT_HAVE_OFFLINE_COMMANDS
  options.dicom_nifti = brainshift::cli::dicom_series_nifti;
  options.nrrd_nifti = brainshift::cli::nrrd_nifti;
  options.nrrd_outputs = brainshift::cli::write_nrrd_outputs;
#endif
  int exit_code = 0;
  brainshift::cli::add_network_commands(app, options, &exit_code);
#ifdef BRAINSHIFT_HAVE_OFFLINE_COMMANDS
  brainshift::cli::add_offline_commands(app, &exit_code);
#else
  brainshift::cli::add_offline_forwarding(app, argc, argv, &exit_code);
#endif
  try {
    app.parse(argc, argv);
  } catch (const CLI::ParseError& e) {
    const int code = app.exit(e);
    return code == 0 ? 0 : brainshift::cli::kExitUsage;
  }
  return exit_code;
}

#pragma once
// The `brainshift` the scanner runs for every scan links no engine: its
// start-up is a few ms instead of ~0.05-0.15 s (the engine's ~100 shared
// libraries and their initialisers, measured in docs/PERFORMANCE.md section
// 4). The offline commands (register, phantom) run the engine in-process, so
// `brainshift register ...`, `brainshift phantom ...`, `brainshift pull
// --format nrrd ...` and the converting pushes execute the full CLI,
// brainshift-offline, installed beside it, with the same arguments. (`pull
// --scene` does not: the daemon serves the label table that names the scene.)
#include <CLI/CLI.hpp>

#include <string>

namespace brainshift::cli {

// The name of the full CLI beside this executable.
inline constexpr const char* kOfflineExecutable = "brainshift-offline";

// Adds register and phantom as subcommands that hand the whole command line
// to brainshift-offline (exec; its exit code is the command's). Sets
// *exit_code to kExitUsage with a message when that executable is missing.
void add_offline_forwarding(CLI::App& app, int argc, char** argv, int* exit_code);

// Replaces this process with brainshift-offline and the same arguments;
// returns kExitUsage (with a message) only when that fails.
int exec_offline(int argc, char** argv);

// `pull ... --format` (NRRD is written by brainshift-offline).
bool is_nrrd_pull(int argc, char** argv);
// `push ... --dicom`, or a push of .nrrd/.nhdr files: brainshift-offline
// reads them (input_conversion.h) and sends NIfTI.
bool is_converting_push(int argc, char** argv);
// A .nrrd or .nhdr file name (a .seg.nrrd too), by its extension.
bool is_nrrd_name(const std::string& path);

}  // namespace brainshift::cli

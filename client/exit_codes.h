#pragma once
// The exit codes of every `brainshift` command, network and offline (README
// "Exit codes", `brainshift --help`). One table: a code means the same thing
// whichever command returns it.
namespace brainshift::cli {

inline constexpr int kExitOk = 0;           // done; a registration gave its non-rigid result
inline constexpr int kExitError = 1;        // the server answered with an error, or register/phantom failed
inline constexpr int kExitUsage = 2;        // bad command line, or a local file a network command cannot use
inline constexpr int kExitUnreachable = 3;  // no answer within the timeout (or the handshake was refused)
inline constexpr int kExitFallback = 4;     // the result is the affine-only fallback (register, push --wait)
inline constexpr int kExitScanFailed = 5;   // the daemon failed to register the scan (push --wait, pull)

inline constexpr const char* kExitCodesHelp =
    "Exit codes: 0 ok (a registration: the non-rigid result); 1 the server answered with an error, or "
    "register/phantom failed; 2 usage, or a local file a network command cannot read or write; 3 timeout or "
    "server unreachable; 4 the result is the AFFINE-ONLY fallback (register, push --wait); 5 the daemon's "
    "registration of the scan failed (push --wait, pull).";

}  // namespace brainshift::cli

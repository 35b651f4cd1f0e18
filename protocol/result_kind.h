#pragma once
// Whether a registration result is the non-rigid one or the affine-only
// fallback a quality gate chose instead (PROTOCOL.md 5.4, 17). One enum and
// one spelling for every place that carries it: event.scan.done,
// scan.result.reply and scan.list.reply ("kind"), metrics.json ("result"),
// the daemon's store and the OpenIGTLink STATUS. Header-only and free of
// any library, so the engine may include it (DESIGN.md, "One vocabulary at
// the seams"). The enumerators are spelled as on the wire.
#include <optional>
#include <string_view>

namespace brainshift::protocol {

enum class ResultKind {
  nonrigid,              // the elastic correction passed every quality gate
  affine_only_fallback,  // a gate refused it; the field is the affine alone
};

constexpr std::string_view to_string(ResultKind kind) {
  return kind == ResultKind::nonrigid ? "nonrigid" : "affine_only_fallback";
}

constexpr std::optional<ResultKind> result_kind_from_string(std::string_view text) {
  for (ResultKind k : {ResultKind::nonrigid, ResultKind::affine_only_fallback})
    if (to_string(k) == text) return k;
  return std::nullopt;
}

}  // namespace brainshift::protocol

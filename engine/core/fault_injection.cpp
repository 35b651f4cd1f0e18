#include "core/fault_injection.h"

#include <cstdlib>
#include <regex>

#include "core/errors.h"

namespace brainshift {

InjectedFault parse_injected_fault(const std::string& text) {
  static const std::regex form(R"(([a-z_]+)@([0-9]{1,4})(#([0-9]{1,6}))?)");
  std::smatch m;
  if (!std::regex_match(text, m, form))
    throw InputError("BRAINSHIFT_INJECT_FAULT=\"" + text + "\": expected <stage>@<rank>[#<n>], e.g. solve@1#1");
  InjectedFault f;
  f.stage = m[1].str();
  if (f.stage != "solve" && f.stage != "result_write")
    throw InputError("BRAINSHIFT_INJECT_FAULT: unknown stage \"" + f.stage + "\" (known: solve, result_write)");
  f.rank = std::stoi(m[2].str());
  f.nth = m[4].matched ? std::stoi(m[4].str()) : 0;
  return f;
}

const std::optional<InjectedFault>& injected_fault() {
  static const std::optional<InjectedFault> fault = []() -> std::optional<InjectedFault> {
    const char* value = std::getenv("BRAINSHIFT_INJECT_FAULT");
    if (!value || !*value) return std::nullopt;
    return parse_injected_fault(value);
  }();
  return fault;
}

bool FaultPoint::fires(int rank) {
  const auto& fault = injected_fault();
  if (!fault || fault->stage != stage_ || fault->rank != rank) return false;
  ++calls_;
  return fault->nth == 0 || fault->nth == calls_;
}

}  // namespace brainshift

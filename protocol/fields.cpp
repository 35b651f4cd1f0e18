#include "protocol/fields.h"

#include <cstdint>
#include <cmath>

namespace brainshift::protocol::detail {

using nlohmann::json;

FieldReader::FieldReader(const json& object, std::string context)
    : object_(object), context_(std::move(context)) {
  if (!object_.is_object())
    throw ProtocolError(ErrorCode::kInvalidRequest, context_ + ": expected a JSON object");
}

void FieldReader::fail(const char* key, const std::string& what) const {
  throw ProtocolError(ErrorCode::kInvalidRequest,
                      context_ + ": field \"" + key + "\" " + what);
}

const json* FieldReader::find(const char* key) const {
  const auto it = object_.find(key);
  if (it == object_.end() || it->is_null()) return nullptr;
  return &*it;
}

std::optional<std::string> FieldReader::opt_string(const char* key) const {
  const json* v = find(key);
  if (!v) return std::nullopt;
  if (!v->is_string() || v->get_ref<const std::string&>().empty())
    fail(key, "must be a non-empty string");
  return v->get<std::string>();
}

std::string FieldReader::text(const char* key) const {
  const json* v = find(key);
  if (!v) return "";
  if (!v->is_string()) fail(key, "must be a string");
  return v->get<std::string>();
}

std::string FieldReader::string(const char* key) const {
  auto s = opt_string(key);
  if (!s) fail(key, "is required (non-empty string)");
  return *s;
}

std::optional<std::uint64_t> FieldReader::opt_uint(const char* key) const {
  const json* v = find(key);
  if (!v) return std::nullopt;
  // A json built in memory from an int is signed even when the value is >= 0.
  if (!v->is_number_integer() || (!v->is_number_unsigned() && v->get<std::int64_t>() < 0))
    fail(key, "must be a non-negative integer");
  return v->get<std::uint64_t>();
}

std::uint64_t FieldReader::uint(const char* key) const {
  auto u = opt_uint(key);
  if (!u) fail(key, "is required (non-negative integer)");
  return *u;
}

double FieldReader::number(const char* key) const {
  const json* v = find(key);
  if (!v || !v->is_number() || !std::isfinite(v->get<double>()))
    fail(key, "is required (finite number)");
  return v->get<double>();
}

double FieldReader::fraction(const char* key) const {
  const double f = number(key);
  if (f < 0.0 || f > 1.0) fail(key, "must lie in [0, 1]");
  return f;
}

bool FieldReader::boolean(const char* key, bool fallback) const {
  const json* v = find(key);
  if (!v) return fallback;
  if (!v->is_boolean()) fail(key, "must be true or false");
  return v->get<bool>();
}

const json* FieldReader::opt_array(const char* key) const {
  const json* v = find(key);
  if (v && !v->is_array()) fail(key, "must be an array");
  return v;
}

const json& FieldReader::array(const char* key) const {
  const json* v = opt_array(key);
  if (!v) fail(key, "is required (array)");
  return *v;
}

const json* FieldReader::opt_object(const char* key) const {
  const json* v = find(key);
  if (v && !v->is_object()) fail(key, "must be an object");
  return v;
}

const json& FieldReader::object(const char* key) const {
  const json* v = opt_object(key);
  if (!v) fail(key, "is required (object)");
  return *v;
}

namespace {

// Well-formed UTF-8 (no overlong forms, no surrogates, at most U+10FFFF):
// what a JSON header may hold.
bool is_utf8(const std::string& s) {
  std::size_t i = 0;
  while (i < s.size()) {
    const auto c = static_cast<unsigned char>(s[i]);
    const std::size_t n = c < 0x80 ? 1 : (c >> 5) == 0x6 ? 2 : (c >> 4) == 0xE ? 3 : (c >> 3) == 0x1E ? 4 : 0;
    if (n == 0 || i + n > s.size()) return false;
    std::uint32_t cp = n == 1 ? c : n == 2 ? (c & 0x1Fu) : n == 3 ? (c & 0x0Fu) : (c & 0x07u);
    for (std::size_t k = 1; k < n; ++k) {
      const auto cc = static_cast<unsigned char>(s[i + k]);
      if ((cc >> 6) != 0x2) return false;
      cp = (cp << 6) | (cc & 0x3Fu);
    }
    const std::uint32_t min_cp[] = {0, 0, 0x80, 0x800, 0x10000};
    if (cp < min_cp[n] || cp > 0x10FFFF || (cp >= 0xD800 && cp <= 0xDFFF)) return false;
    i += n;
  }
  return true;
}

}  // namespace

std::optional<std::string> normalised_patient_id(const std::string& id) {
  if (id.size() > 64 || !is_utf8(id)) return std::nullopt;
  for (const char c : id)
    if (static_cast<unsigned char>(c) < 0x20 || c == 0x7f) return std::nullopt;
  const auto first = id.find_first_not_of(' ');
  if (first == std::string::npos) return std::nullopt;
  return id.substr(first, id.find_last_not_of(' ') - first + 1);
}

bool is_valid_id(const std::string& id) {
  if (id.empty() || id.size() > 128) return false;
  for (char c : id)
    if (c < 0x21 || c > 0x7e) return false;
  return true;
}

}  // namespace brainshift::protocol::detail

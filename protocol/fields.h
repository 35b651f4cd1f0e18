#pragma once
// Internal helper for the typed parsers: reads fields of a JSON object and
// throws ProtocolError(kInvalidRequest) naming the message and the field, so
// every refusal tells the sender exactly what to fix.
#include <cstdint>
#include <optional>
#include <string>

#include <nlohmann/json.hpp>

#include "protocol/error_codes.h"

namespace brainshift::protocol::detail {

class FieldReader {
 public:
  FieldReader(const nlohmann::json& object, std::string context);

  std::string string(const char* key) const;  // required, non-empty
  std::optional<std::string> opt_string(const char* key) const;
  // Free text that may be empty (messages, reasons); "" when absent.
  std::string text(const char* key) const;
  std::uint64_t uint(const char* key) const;
  std::optional<std::uint64_t> opt_uint(const char* key) const;
  double number(const char* key) const;  // finite
  double fraction(const char* key) const;  // in [0, 1]
  bool boolean(const char* key, bool fallback) const;
  const nlohmann::json& array(const char* key) const;
  const nlohmann::json* opt_array(const char* key) const;
  const nlohmann::json& object(const char* key) const;
  const nlohmann::json* opt_object(const char* key) const;
  bool has(const char* key) const { return object_.contains(key); }

  [[noreturn]] void fail(const char* key, const std::string& what) const;

 private:
  const nlohmann::json* find(const char* key) const;
  const nlohmann::json& object_;
  std::string context_;
};

// Printable ASCII, 1..128 characters: ids chosen by clients or the server.
bool is_valid_id(const std::string& id);

// A patient's identifier as DICOM's PatientID (0010,0020) holds it: 1..64
// bytes of UTF-8, no control characters, not only spaces. Returned without the
// leading and trailing spaces DICOM pads with (they are not significant), or
// nullopt when invalid.
std::optional<std::string> normalised_patient_id(const std::string& id);
// That rule in words, for every message that refuses an identifier.
inline constexpr const char* kPatientIdRule =
    "1..64 bytes of UTF-8 without control characters, not only spaces (DICOM PatientID)";

}  // namespace brainshift::protocol::detail

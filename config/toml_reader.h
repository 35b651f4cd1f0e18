#pragma once
// The one TOML reader behind brainshift's configuration files
// (brainshiftd.toml, labels.toml, the client allow-list): parsing, typed values
// with ranges and an unknown-key check, every error an InputError that names
// "source: [section] key: what". It needs only toml++ and core/errors.h, not
// the engine, so the server core reads its settings with it as well as
// config_file.cpp does the pipeline parameters.
#include <cstdint>
#include <filesystem>
#include <initializer_list>
#include <limits>
#include <set>
#include <string>
#include <string_view>
#include <type_traits>
#include <vector>

#include <toml++/toml.h>

namespace brainshift::config {

// Throws InputError "source: TOML parse error at line N: ..." on a syntax error.
toml::table parse_toml(const std::string& text, const std::string& source);
// (A whole file is read with read_whole_file, core/file_bytes.h.)

// An interval of real values: bounds may be open, closed or infinite.
struct Interval {
  double lo = -std::numeric_limits<double>::infinity();
  double hi = std::numeric_limits<double>::infinity();
  bool lo_open = false, hi_open = false;

  static Interval above(double lo) { return {lo, std::numeric_limits<double>::infinity(), true, false}; }
  static Interval at_least(double lo) { return {lo, std::numeric_limits<double>::infinity(), false, false}; }
  static Interval open(double lo, double hi) { return {lo, hi, true, true}; }
  static Interval closed(double lo, double hi) { return {lo, hi, false, false}; }
  bool contains(double v) const;  // never NaN
  std::string describe() const;   // "> 0", ">= 0", "in (0, 1)", "in [0, 1]"
};

// One table of a TOML document, read key by key. Every key asked for is
// remembered, so that reject_unknown_keys() can name a typo instead of letting
// it fall back silently to a default. A missing key gives the fallback; a
// missing table (nullptr) behaves as an empty one.
class TomlSection {
 public:
  // name: the section as messages show it ("server", "surface.outer"); empty
  // for the document's root.
  TomlSection(const toml::table* table, std::string source, std::string name);

  std::string string(std::string_view key, const std::string& fallback);
  std::int64_t integer(std::string_view key, std::int64_t fallback, std::int64_t lo, std::int64_t hi);
  // An integer is accepted where a real number is expected (cell_size_mm = 3).
  double number(std::string_view key, double fallback, const Interval& range = {});
  bool boolean(std::string_view key, bool fallback);
  std::vector<std::string> strings(std::string_view key, const std::vector<std::string>& fallback = {});
  // A sub-table ([surface.outer] within [surface], or an inline table), named
  // "<name>.<key>"; absent: a section without a table.
  TomlSection table(std::string_view key);
  // The tables of an array of tables ([[key]]), named "<name>.<key>[i]".
  std::vector<TomlSection> tables(std::string_view key);
  // The raw value, for a key that takes more than one type; nullptr when absent.
  const toml::node* node(std::string_view key);

  // Reads a field of a parameter struct, the field's value being the default
  // and its type the TOML type (bool, integers within the type's range, real
  // numbers, strings).
  template <class T>
  void read(std::string_view key, T& field);
  // An integer field within [lo, hi].
  template <class T>
  void read(std::string_view key, T& field, std::int64_t lo, std::int64_t hi) {
    static_assert(std::is_integral_v<T> && !std::is_same_v<T, bool>);
    field = static_cast<T>(integer(key, static_cast<std::int64_t>(field), lo, hi));
  }
  // A real-valued field within range.
  void read(std::string_view key, double& field, const Interval& range) { field = number(key, field, range); }

  // Keys read by someone else (e.g. [server] among the pipeline's sections).
  void allow(std::initializer_list<std::string_view> keys);
  // InputError "source: [name] key: what" for the first key not asked for.
  void reject_unknown_keys(std::string_view what = "unknown key") const;
  [[noreturn]] void fail(std::string_view key, const std::string& what) const;
  // "source: [name] what", for a rule over several keys.
  [[noreturn]] void fail(const std::string& what) const;

  bool present() const { return table_ != nullptr; }
  const std::string& source() const { return source_; }
  const std::string& name() const { return name_; }

 private:
  const toml::node* find(std::string_view key);
  std::string child_name(std::string_view key) const;

  const toml::table* table_;
  std::string source_, name_;
  std::set<std::string, std::less<>> known_;
};

template <class T>
void TomlSection::read(std::string_view key, T& field) {
  if constexpr (std::is_same_v<T, bool>) {
    field = boolean(key, field);
  } else if constexpr (std::is_integral_v<T>) {
    using Limits = std::numeric_limits<T>;
    constexpr bool wider = std::is_unsigned_v<T> && sizeof(T) >= sizeof(std::int64_t);
    constexpr std::int64_t hi =
        wider ? std::numeric_limits<std::int64_t>::max() : static_cast<std::int64_t>(Limits::max());
    read(key, field, static_cast<std::int64_t>(Limits::min()), hi);
  } else if constexpr (std::is_floating_point_v<T>) {
    field = static_cast<T>(number(key, field));
  } else {
    field = string(key, field);
  }
}

}  // namespace brainshift::config

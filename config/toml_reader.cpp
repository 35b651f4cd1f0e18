#include "config/toml_reader.h"

#include <cmath>
#include <fstream>
#include <sstream>

#include "core/errors.h"

namespace brainshift::config {
namespace {

std::string format(double v) {
  std::ostringstream s;
  s << v;
  return s.str();
}

}  // namespace

toml::table parse_toml(const std::string& text, const std::string& source) {
  try {
    return toml::parse(text, source);
  } catch (const toml::parse_error& e) {
    std::ostringstream msg;
    msg << source << ": TOML parse error at line " << e.source().begin.line << ": " << e.description();
    throw InputError(msg.str());
  }
}

bool Interval::contains(double v) const {
  return (lo_open ? v > lo : v >= lo) && (hi_open ? v < hi : v <= hi);
}

std::string Interval::describe() const {
  const bool has_lo = std::isfinite(lo), has_hi = std::isfinite(hi);
  if (has_lo && has_hi)
    return std::string("in ") + (lo_open ? "(" : "[") + format(lo) + ", " + format(hi) + (hi_open ? ")" : "]");
  if (has_lo) return (lo_open ? "> " : ">= ") + format(lo);
  if (has_hi) return (hi_open ? "< " : "<= ") + format(hi);
  return "a number";
}

TomlSection::TomlSection(const toml::table* table, std::string source, std::string name)
    : table_(table), source_(std::move(source)), name_(std::move(name)) {}

const toml::node* TomlSection::find(std::string_view key) {
  known_.emplace(key);
  return table_ ? table_->get(key) : nullptr;
}

std::string TomlSection::child_name(std::string_view key) const {
  return name_.empty() ? std::string(key) : name_ + "." + std::string(key);
}

void TomlSection::fail(std::string_view key, const std::string& what) const {
  fail(std::string(key) + ": " + what);
}

void TomlSection::fail(const std::string& what) const {
  throw InputError(source_ + ": " + (name_.empty() ? "" : "[" + name_ + "] ") + what);
}

std::string TomlSection::string(std::string_view key, const std::string& fallback) {
  const toml::node* n = find(key);
  if (!n) return fallback;
  if (!n->is_string()) fail(key, "must be a string");
  return n->as_string()->get();
}

std::int64_t TomlSection::integer(std::string_view key, std::int64_t fallback, std::int64_t lo, std::int64_t hi) {
  const toml::node* n = find(key);
  if (!n) return fallback;
  if (!n->is_integer()) fail(key, "must be an integer");
  const std::int64_t v = n->as_integer()->get();
  if (v >= lo && v <= hi) return v;
  const std::string got = ", got " + std::to_string(v);
  // The limits of a C++ type say nothing to the reader of a configuration file.
  if (hi == std::numeric_limits<std::int64_t>::max()) fail(key, "must be >= " + std::to_string(lo) + got);
  if (lo == std::numeric_limits<std::int64_t>::min()) fail(key, "must be <= " + std::to_string(hi) + got);
  fail(key, "must be in [" + std::to_string(lo) + ", " + std::to_string(hi) + "]" + got);
}

double TomlSection::number(std::string_view key, double fallback, const Interval& range) {
  const toml::node* n = find(key);
  if (!n) return fallback;
  double v = 0;
  if (n->is_integer()) v = static_cast<double>(n->as_integer()->get());
  else if (n->is_floating_point()) v = n->as_floating_point()->get();
  else fail(key, "must be a number");
  if (!range.contains(v)) fail(key, "must be " + range.describe() + ", got " + format(v));
  return v;
}

bool TomlSection::boolean(std::string_view key, bool fallback) {
  const toml::node* n = find(key);
  if (!n) return fallback;
  if (!n->is_boolean()) fail(key, "must be true or false");
  return n->as_boolean()->get();
}

std::vector<std::string> TomlSection::strings(std::string_view key, const std::vector<std::string>& fallback) {
  const toml::node* n = find(key);
  if (!n) return fallback;
  const toml::array* a = n->as_array();
  if (!a) fail(key, "must be an array of strings");
  std::vector<std::string> out;
  for (const toml::node& item : *a) {
    if (!item.is_string()) fail(key, "must be an array of strings");
    out.push_back(item.as_string()->get());
  }
  return out;
}

TomlSection TomlSection::table(std::string_view key) {
  const toml::node* n = find(key);
  if (n && !n->is_table()) throw InputError(source_ + ": [" + child_name(key) + "] must be a table");
  return TomlSection(n ? n->as_table() : nullptr, source_, child_name(key));
}

std::vector<TomlSection> TomlSection::tables(std::string_view key) {
  const toml::node* n = find(key);
  std::vector<TomlSection> out;
  if (!n) return out;
  const toml::array* a = n->as_array();
  if (!a || (!a->empty() && !a->is_array_of_tables()))
    fail(key, "must be an array of tables [[" + child_name(key) + "]]");
  for (std::size_t i = 0; i < a->size(); ++i)
    out.emplace_back(a->get(i)->as_table(), source_, child_name(key) + "[" + std::to_string(i) + "]");
  return out;
}

const toml::node* TomlSection::node(std::string_view key) { return find(key); }

void TomlSection::allow(std::initializer_list<std::string_view> keys) {
  for (std::string_view k : keys) known_.emplace(k);
}

void TomlSection::reject_unknown_keys(std::string_view what) const {
  if (!table_) return;
  for (const auto& [key, value] : *table_)
    if (!known_.count(key.str())) fail(key.str(), std::string(what));
}

}  // namespace brainshift::config

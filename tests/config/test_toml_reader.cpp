// The shared TOML layer (config/toml_reader.h): every error names the source,
// the section and the key, and no key goes unread without an error.
#include <fstream>
#include <functional>
#include <limits>
#include <string>

#include <gtest/gtest.h>

#include "config/toml_reader.h"
#include "core/errors.h"
#include "core/file_bytes.h"
#include "temp_dir.h"

namespace brainshift::config {
namespace {

std::string error_of(const std::function<void()>& f) {
  try {
    f();
  } catch (const InputError& e) {
    return e.what();
  }
  return "(accepted)";
}

// The message of reading `key` from [s] of `text` with `get`.
std::string section_error(const std::string& text, const std::function<void(TomlSection&)>& get) {
  return error_of([&] {
    const toml::table doc = parse_toml(text, "case.toml");
    TomlSection root(&doc, "case.toml", "");
    TomlSection s = root.table("s");
    get(s);
  });
}

TEST(TomlReader, SyntaxErrorNamesTheSourceAndLine) {
  const std::string why = error_of([] { parse_toml("[server]\nport = 1\n[broken\n", "case.toml"); });
  EXPECT_NE(why.find("case.toml: TOML parse error at line 3"), std::string::npos) << why;
}

TEST(TomlReader, MissingFileIsNamed) {
  test::TempDir dir("toml");
  const std::string why = error_of([&] { read_whole_file(dir / "absent.toml", "client allow-list"); });
  EXPECT_NE(why.find("absent.toml: cannot open the client allow-list"), std::string::npos) << why;
  EXPECT_NE(error_of([&] { read_whole_file(dir.path(), "label map"); }).find("not a regular file"), std::string::npos);
  std::ofstream(dir / "present.toml") << "a = 1\n";
  EXPECT_EQ(read_whole_file(dir / "present.toml"), "a = 1\n");
}

TEST(TomlReader, TypedValuesAndFallbacks) {
  const toml::table doc = parse_toml(
      "[s]\nname = \"or1\"\ncount = 7\nratio = 0.25\nwhole = 3\nflag = true\nlist = [\"a\", \"b\"]\n"
      "[s.inner]\nx = 2\n",
      "t");
  TomlSection s(doc.get_as<toml::table>("s"), "t", "s");
  EXPECT_EQ(s.string("name", "x"), "or1");
  EXPECT_EQ(s.integer("count", 0, 1, 10), 7);
  EXPECT_DOUBLE_EQ(s.number("ratio", 0, Interval::open(0, 1)), 0.25);
  EXPECT_DOUBLE_EQ(s.number("whole", 0), 3.0);  // an integer where a real number is expected
  EXPECT_TRUE(s.boolean("flag", false));
  EXPECT_EQ(s.strings("list"), (std::vector<std::string>{"a", "b"}));
  TomlSection inner = s.table("inner");
  EXPECT_EQ(inner.name(), "s.inner");
  EXPECT_EQ(inner.integer("x", 0, 0, 5), 2);
  // Absent keys and tables give the fallback.
  EXPECT_EQ(s.string("absent", "fallback"), "fallback");
  EXPECT_EQ(s.integer("absent", 42, 0, 1), 42);
  EXPECT_FALSE(s.table("none").present());
  EXPECT_EQ(s.table("none").integer("x", 5, 0, 1), 5);
  EXPECT_NO_THROW(s.reject_unknown_keys());
}

TEST(TomlReader, WrongTypesAndRangesNameSourceSectionAndKey) {
  auto get_int = [](TomlSection& s) { s.integer("k", 0, 1, 10); };
  auto get_num = [](TomlSection& s) { s.number("k", 0.5, Interval::open(0, 1)); };
  EXPECT_EQ(section_error("[s]\nk = \"4\"\n", get_int), "case.toml: [s] k: must be an integer");
  EXPECT_EQ(section_error("[s]\nk = 1.5\n", get_int), "case.toml: [s] k: must be an integer");
  EXPECT_EQ(section_error("[s]\nk = 11\n", get_int), "case.toml: [s] k: must be in [1, 10], got 11");
  EXPECT_EQ(section_error("[s]\nk = 1.0\n", get_num), "case.toml: [s] k: must be in (0, 1), got 1");
  EXPECT_EQ(section_error("[s]\nk = nan\n", get_num), "case.toml: [s] k: must be in (0, 1), got nan");
  EXPECT_EQ(section_error("[s]\nk = true\n", get_num), "case.toml: [s] k: must be a number");
  EXPECT_EQ(section_error("[s]\nk = 0\n", [](TomlSection& s) { s.number("k", 1, Interval::above(0)); }),
            "case.toml: [s] k: must be > 0, got 0");
  EXPECT_EQ(section_error("[s]\nk = -1\n", [](TomlSection& s) { s.number("k", 1, Interval::at_least(0)); }),
            "case.toml: [s] k: must be >= 0, got -1");
  EXPECT_EQ(section_error("[s]\nk = 1\n", [](TomlSection& s) { s.boolean("k", false); }),
            "case.toml: [s] k: must be true or false");
  EXPECT_EQ(section_error("[s]\nk = 1\n", [](TomlSection& s) { s.string("k", ""); }),
            "case.toml: [s] k: must be a string");
  EXPECT_EQ(section_error("[s]\nk = [\"a\", 1]\n", [](TomlSection& s) { s.strings("k"); }),
            "case.toml: [s] k: must be an array of strings");
  EXPECT_EQ(section_error("[s]\nk = 1\n", [](TomlSection& s) { s.table("k"); }),
            "case.toml: [s.k] must be a table");
  EXPECT_EQ(section_error("s = 1\n", [](TomlSection&) {}), "case.toml: [s] must be a table");
}

TEST(TomlReader, FieldsKeepTheirTypeRange) {
  struct {
    unsigned seed = 3;
    std::size_t bytes = 10;
    int sweeps = 1;
    double size_mm = 1.0;
    bool on = false;
    std::string name = "x";
  } f;
  const toml::table doc = parse_toml("seed = 9\nbytes = 4096\nsize_mm = 2\non = true\n", "t");
  TomlSection root(&doc, "t", "");
  root.read("seed", f.seed);
  root.read("bytes", f.bytes);
  root.read("sweeps", f.sweeps);
  root.read("size_mm", f.size_mm);
  root.read("on", f.on);
  root.read("name", f.name);
  EXPECT_EQ(f.seed, 9u);
  EXPECT_EQ(f.bytes, 4096u);
  EXPECT_EQ(f.sweeps, 1);  // absent: the field's own default
  EXPECT_DOUBLE_EQ(f.size_mm, 2.0);
  EXPECT_TRUE(f.on);
  EXPECT_EQ(f.name, "x");

  auto read_unsigned = [](TomlSection& s) {
    std::size_t n = 0;
    s.read("k", n);
  };
  EXPECT_EQ(section_error("[s]\nk = -3\n", read_unsigned), "case.toml: [s] k: must be >= 0, got -3");
  auto read_int = [](TomlSection& s) {
    int n = 0;
    s.read("k", n);
  };
  const std::string too_big = section_error("[s]\nk = 4294967296\n", read_int);
  EXPECT_NE(too_big.find("case.toml: [s] k: must be in [-2147483648, 2147483647]"), std::string::npos) << too_big;
  auto read_bounded = [](TomlSection& s) {
    std::size_t n = 4;
    s.read("k", n, 1, 1000);
  };
  EXPECT_EQ(section_error("[s]\nk = 0\n", read_bounded), "case.toml: [s] k: must be in [1, 1000], got 0");
}

TEST(TomlReader, UnknownKeysAreNamedUnlessReadOrAllowed) {
  const toml::table doc = parse_toml("[s]\nendpoint = \"a\"\nendpont = \"b\"\n[other]\nx = 1\n", "case.toml");
  TomlSection root(&doc, "case.toml", "");
  TomlSection s = root.table("s");
  s.string("endpoint", "");
  EXPECT_EQ(error_of([&] { s.reject_unknown_keys(); }), "case.toml: [s] endpont: unknown key");
  EXPECT_EQ(error_of([&] { root.reject_unknown_keys("unknown section"); }), "case.toml: other: unknown section");
  root.allow({"other"});
  EXPECT_NO_THROW(root.reject_unknown_keys());
  // A sub-table that nobody reads is a typo too ([surface.outr]).
  const toml::table nested = parse_toml("[surface.outr]\nstep = 1\n", "case.toml");
  TomlSection surface = TomlSection(&nested, "case.toml", "").table("surface");
  surface.table("outer");
  EXPECT_EQ(error_of([&] { surface.reject_unknown_keys(); }), "case.toml: [surface] outr: unknown key");
}

TEST(TomlReader, ArraysOfTablesNameEachEntry) {
  const toml::table doc = parse_toml("[[clients]]\nname = \"a\"\n[[clients]]\nname = 5\n", "list.toml");
  TomlSection root(&doc, "list.toml", "");
  std::vector<TomlSection> entries = root.tables("clients");
  ASSERT_EQ(entries.size(), 2u);
  EXPECT_EQ(entries[0].string("name", ""), "a");
  EXPECT_EQ(error_of([&] { entries[1].string("name", ""); }), "list.toml: [clients[1]] name: must be a string");
  EXPECT_TRUE(root.tables("absent").empty());

  const toml::table bad = parse_toml("clients = 5\nmixed = [{ a = 1 }, 2]\nnone = []\n", "list.toml");
  TomlSection b(&bad, "list.toml", "");
  EXPECT_EQ(error_of([&] { b.tables("clients"); }), "list.toml: clients: must be an array of tables [[clients]]");
  EXPECT_EQ(error_of([&] { b.tables("mixed"); }), "list.toml: mixed: must be an array of tables [[mixed]]");
  EXPECT_TRUE(b.tables("none").empty());
}

}  // namespace
}  // namespace brainshift::config

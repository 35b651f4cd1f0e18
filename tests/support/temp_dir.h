#pragma once
// The tests' one temporary folder: a fresh, unique directory (mkdtemp) under
// the system temp folder, removed with everything in it when the object goes.
// Unique per object, so tests running in parallel (ctest -j) never share one.
#include <filesystem>
#include <string>

namespace brainshift::test {

class TempDir {
 public:
  explicit TempDir(const std::string& tag = "test");
  ~TempDir();
  TempDir(const TempDir&) = delete;
  TempDir& operator=(const TempDir&) = delete;

  const std::filesystem::path& path() const { return path_; }
  // path() / name, as a convenience for files in it.
  std::filesystem::path operator/(const std::string& name) const { return path_ / name; }

 private:
  std::filesystem::path path_;
};

}  // namespace brainshift::test

#pragma once
// The tests' one temporary folder: a fresh, unique directory (mkdtemp) under
// the system temp folder, removed with everything in it when the object goes
// (unless keep() was called: a failed end-to-end test leaves its logs).
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
  // Leave the folder on disk when destroyed, and say where on stdout.
  void keep() { keep_ = true; }
  // path() / name, as a convenience for files in it.
  std::filesystem::path operator/(const std::string& name) const { return path_ / name; }

 private:
  std::filesystem::path path_;
  bool keep_ = false;
};

}  // namespace brainshift::test

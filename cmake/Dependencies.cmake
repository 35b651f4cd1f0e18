# Every dependency is a Debian 12 package listed in .ci/packages.txt.
# Found through CMake config files or pkg-config, never hard-coded paths.
find_package(PkgConfig REQUIRED)
find_package(MPI REQUIRED COMPONENTS C CXX)
pkg_check_modules(PETSC REQUIRED IMPORTED_TARGET PETSc)
find_package(Eigen3 3.4 REQUIRED NO_MODULE)
find_package(CGAL REQUIRED)
set(HDF5_PREFER_PARALLEL TRUE)
find_package(HDF5 REQUIRED COMPONENTS C)
find_package(cppzmq REQUIRED)
find_package(nlohmann_json REQUIRED)
find_package(tomlplusplus REQUIRED)
find_package(spdlog REQUIRED)
find_package(CLI11 REQUIRED)
find_package(ZLIB REQUIRED)
find_package(PNG REQUIRED)
find_package(GTest REQUIRED)
find_package(Threads REQUIRED)

# NIfTI: only the reference header layouts (nifti1.h, nifti2.h of
# libnifti2-dev), included as <nifti/nifti2.h>; niftilib itself is not linked
# (docs/DESIGN.md, "NIfTI I/O"). Its NIFTIConfig.cmake is not used: it points
# NIFTI::znz at a file Debian does not ship.
find_path(NIFTI_HEADERS_DIR nifti/nifti2.h REQUIRED)

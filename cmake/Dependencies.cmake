# Every dependency is a Debian 12 package listed in .ci/packages.txt.
# Found through CMake config files or pkg-config, never hard-coded paths.
find_package(PkgConfig REQUIRED)
find_package(MPI REQUIRED COMPONENTS C CXX)
pkg_check_modules(PETSC REQUIRED IMPORTED_TARGET PETSc)
# report.png is drawn and encoded with Cairo (no second PNG writer).
pkg_check_modules(CAIRO REQUIRED IMPORTED_TARGET cairo)
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
find_package(Threads REQUIRED)

# Debian's NIFTIConfig.cmake points NIFTI::znz at a file that does not exist,
# so niftilib is located by hand (still without hard-coded paths).
find_path(NIFTI_INCLUDE_DIR nifti1_io.h PATH_SUFFIXES nifti REQUIRED)
find_library(NIFTI_IO_LIBRARY niftiio REQUIRED)
find_library(NIFTI_ZNZ_LIBRARY NAMES znz libznz.so.3 REQUIRED)
add_library(brainshift_nifti INTERFACE)
target_include_directories(brainshift_nifti SYSTEM INTERFACE ${NIFTI_INCLUDE_DIR})
target_link_libraries(brainshift_nifti INTERFACE ${NIFTI_IO_LIBRARY} ${NIFTI_ZNZ_LIBRARY} ZLIB::ZLIB m)

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

# NIfTI: only the reference header layouts (nifti1.h, nifti2.h of
# libnifti2-dev), included as <nifti/nifti2.h>; niftilib itself is not linked
# (docs/DESIGN.md, "NIfTI I/O"). Its NIFTIConfig.cmake is not used: it points
# NIFTI::znz at a file Debian does not ship.
find_path(NIFTI_HEADERS_DIR nifti/nifti2.h REQUIRED)

# DCMTK (Debian's libdcmtk-dev): DICOM series in (engine/image/dicom_series.h,
# dcmdata only); the tests write their DICOM series with it too.
find_package(DCMTK REQUIRED CONFIG)

# OpenIGTLink 1.11 (protocol version 2: IMAGE, POLYDATA, STATUS), for the
# gateway to 3D Slicer. Debian installs OpenIGTLinkConfig.cmake under
# /usr/lib/openigtlink, which find_package searches by name; it defines paths
# but no imported target, and its REQUIRED_*_FLAGS (e.g. -fno-tree-vectorize)
# are meant for building the library itself, so only the paths are used.
find_package(OpenIGTLink REQUIRED CONFIG)
if(OpenIGTLink_PROTOCOL_VERSION LESS 2)
  message(FATAL_ERROR "OpenIGTLink protocol version ${OpenIGTLink_PROTOCOL_VERSION}: POLYDATA needs version 2")
endif()
find_library(OPENIGTLINK_LIBRARY OpenIGTLink HINTS ${OpenIGTLink_LIBRARY_DIRS} REQUIRED)
add_library(brainshift_openigtlink INTERFACE)
target_include_directories(brainshift_openigtlink SYSTEM INTERFACE ${OpenIGTLink_INCLUDE_DIRS})
target_link_libraries(brainshift_openigtlink INTERFACE ${OPENIGTLINK_LIBRARY} Threads::Threads)

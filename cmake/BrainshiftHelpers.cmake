# Shared warnings for project targets (not for third-party headers).
function(brainshift_warnings target)
  target_compile_options(${target} PRIVATE -Wall -Wextra -Wpedantic -Wno-unused-parameter)
endfunction()

# The per-scan voxel libraries: GCC's -O2 vectorises only loops that need no
# remainder ("very cheap"), which leaves nearly every row loop of a grid
# scalar; the dynamic cost model vectorises them too. The results are the same
# bits: a loop is vectorised element by element, never reassociated (no
# -ffast-math), and the x86-64 baseline has no FMA to contract into. Not for
# mesh/ (CGAL's filtered predicates) nor fem/ (PETSc).
function(brainshift_vectorise target)
  if(CMAKE_CXX_COMPILER_ID STREQUAL "GNU")
    target_compile_options(${target} PRIVATE -fvect-cost-model=dynamic)
  endif()
endfunction()

# A GoogleTest executable registered with CTest, run serially (one process).
function(brainshift_add_test name)
  cmake_parse_arguments(T "" "" "SOURCES;LIBS;LABELS" ${ARGN})
  add_executable(${name} ${T_SOURCES})
  target_link_libraries(${name} PRIVATE ${T_LIBS} GTest::gtest GTest::gtest_main)
  brainshift_warnings(${name})
  add_test(NAME ${name} COMMAND ${name})
  set_tests_properties(${name} PROPERTIES LABELS "unit;${T_LABELS}")
endfunction()

# Run an existing executable under mpirun with NP ranks. As root Open MPI
# refuses to start without --allow-run-as-root; --oversubscribe lets np exceed
# the two cores of CI machines.
function(brainshift_add_mpi_test name target np)
  add_test(NAME ${name}
           COMMAND ${MPIEXEC_EXECUTABLE} --allow-run-as-root --oversubscribe
                   ${MPIEXEC_NUMPROC_FLAG} ${np} $<TARGET_FILE:${target}> ${ARGN})
  set_tests_properties(${name} PROPERTIES LABELS "mpi" PROCESSORS ${np})
endfunction()

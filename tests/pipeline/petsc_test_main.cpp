// GoogleTest main for tests that need PETSc/MPI alive for the whole run.
#include <gtest/gtest.h>

#include "fem/petsc_session.h"

int main(int argc, char** argv) {
  ::testing::InitGoogleTest(&argc, argv);
  brainshift::PetscSession petsc;
  return RUN_ALL_TESTS();
}

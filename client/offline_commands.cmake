# The client's offline commands (register, phantom) run the engine in-process.
# Defined before client/CMakeLists.txt so the CLI can link them.
add_library(brainshift_offline_commands ${CMAKE_CURRENT_LIST_DIR}/offline_commands.cpp)
target_include_directories(brainshift_offline_commands PUBLIC ${CMAKE_CURRENT_LIST_DIR})
target_link_libraries(brainshift_offline_commands PUBLIC CLI11::CLI11
  PRIVATE brainshift_config brainshift_pipeline brainshift_atlas brainshift_phantom brainshift_fem brainshift_dicom)
brainshift_warnings(brainshift_offline_commands)

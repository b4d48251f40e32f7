# Compiler settings shared by every project target. Nothing here picks a CPU: there is no -march=native
# anywhere, so the same tree cross-compiles; a toolchain file under toolchains/ sets the target instead.

if(NOT CMAKE_BUILD_TYPE AND NOT CMAKE_CONFIGURATION_TYPES)
  set(CMAKE_BUILD_TYPE RelWithDebInfo CACHE STRING "Build type" FORCE)
endif()

set(CMAKE_EXPORT_COMPILE_COMMANDS ON)   # for clang-tidy and clangd

find_program(CVISLAM_CCACHE ccache)
if(CVISLAM_CCACHE AND NOT CMAKE_CXX_COMPILER_LAUNCHER)
  set(CMAKE_CXX_COMPILER_LAUNCHER "${CVISLAM_CCACHE}")
endif()

# Sanitizers apply to everything we compile (tests included) and to the link.
if(CVISLAM_SANITIZE)
  if(NOT CVISLAM_SANITIZE MATCHES "^(address,undefined|address|undefined|thread)$")
    message(FATAL_ERROR "CVISLAM_SANITIZE='${CVISLAM_SANITIZE}': use 'address,undefined' or 'thread'")
  endif()
  add_compile_options(-fsanitize=${CVISLAM_SANITIZE} -fno-omit-frame-pointer -fno-sanitize-recover=all)
  add_link_options(-fsanitize=${CVISLAM_SANITIZE})
endif()

if(CVISLAM_FUZZ)
  if(NOT CMAKE_CXX_COMPILER_ID MATCHES "Clang")
    message(FATAL_ERROR "CVISLAM_FUZZ needs clang (libFuzzer): configure with CXX=clang++-14, or use test/fuzz/run_fuzz.sh")
  endif()
  add_compile_options(-fsanitize=fuzzer-no-link)
endif()

# Warnings for project code only (imported targets are SYSTEM includes, so third-party headers stay quiet).
set(CVISLAM_WARNING_FLAGS -Wall -Wextra -Wshadow -Wnon-virtual-dtor -Wcast-align -Wunused -Woverloaded-virtual
    -Wdouble-promotion -Wformat=2 -Wimplicit-fallthrough)
if(CVISLAM_WERROR)
  list(APPEND CVISLAM_WARNING_FLAGS -Werror)
endif()
# GCC 12 warns about std::string's own operator+ inlined at -O3 (GCC bug 105329: a -Wrestrict false positive
# in libstdc++), seen in the aarch64 build; it says nothing about project code.
if(CMAKE_CXX_COMPILER_ID STREQUAL "GNU" AND CMAKE_CXX_COMPILER_VERSION VERSION_LESS 13)
  list(APPEND CVISLAM_WARNING_FLAGS -Wno-restrict)
endif()
# On aarch64, GCC notes that GCC 10 changed how std::pair is passed: an ABI note about old compilers, not a
# warning about this code (everything here is built with one compiler).
if(CMAKE_CXX_COMPILER_ID STREQUAL "GNU" AND CMAKE_SYSTEM_PROCESSOR MATCHES "aarch64|arm64")
  list(APPEND CVISLAM_WARNING_FLAGS -Wno-psabi)
endif()

# cvislam_target_defaults(<target>): C++20, project warnings, NaN-initialised Eigen matrices in Debug.
function(cvislam_target_defaults target)
  target_compile_features(${target} PUBLIC cxx_std_20)
  set_target_properties(${target} PROPERTIES CXX_EXTENSIONS OFF)
  target_compile_options(${target} PRIVATE ${CVISLAM_WARNING_FLAGS})
  # An uninitialised Eigen matrix shows up as NaN in Debug instead of as plausible garbage.
  target_compile_definitions(${target} PRIVATE $<$<CONFIG:Debug>:EIGEN_INITIALIZE_MATRICES_BY_NAN>)
endfunction()

# cvislam_add_library(<name> ALIAS <ns::name> SOURCES ... PUBLIC_DEPS ... PRIVATE_DEPS ...)
# Include paths are rooted at the repository, so code includes "common/geometry/lie.hpp" and the
# include line reads like the folder layout in DESIGN.md.
function(cvislam_add_library name)
  cmake_parse_arguments(ARG "" "ALIAS" "SOURCES;PUBLIC_DEPS;PRIVATE_DEPS" ${ARGN})
  if(ARG_SOURCES)
    add_library(${name} STATIC ${ARG_SOURCES})
    target_include_directories(${name} PUBLIC "${PROJECT_SOURCE_DIR}")
    target_link_libraries(${name} PUBLIC ${ARG_PUBLIC_DEPS} PRIVATE ${ARG_PRIVATE_DEPS})
    cvislam_target_defaults(${name})
  else()
    add_library(${name} INTERFACE)
    target_include_directories(${name} INTERFACE "${PROJECT_SOURCE_DIR}")
    target_link_libraries(${name} INTERFACE ${ARG_PUBLIC_DEPS})
    target_compile_features(${name} INTERFACE cxx_std_20)
  endif()
  if(ARG_ALIAS)
    add_library(${ARG_ALIAS} ALIAS ${name})
  endif()
endfunction()

# cvislam_add_executable(<name> SOURCES ... DEPS ...)
function(cvislam_add_executable name)
  cmake_parse_arguments(ARG "" "" "SOURCES;DEPS" ${ARGN})
  add_executable(${name} ${ARG_SOURCES})
  target_link_libraries(${name} PRIVATE ${ARG_DEPS})
  cvislam_target_defaults(${name})
  set_target_properties(${name} PROPERTIES RUNTIME_OUTPUT_DIRECTORY "${PROJECT_BINARY_DIR}/bin")
endfunction()

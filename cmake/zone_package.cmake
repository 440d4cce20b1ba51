# The installed CMake package `zone` (docs/embedding.md): `cmake --install` puts the public headers
# in <prefix>/include/zone/, the libraries in <prefix>/lib/ and the package files in
# <prefix>/lib/cmake/zone/. find_package(zone CONFIG) then gives zone::interest (the CPU core) and,
# when this build has CUDA, zone::gpu (the GPU finders). No test, tool or benchmark is installed.
include(CMakePackageConfigHelpers)

set(ZONE_PACKAGE_TARGETS zone_interest)
if(ZONE_HAVE_CUDA)
  list(APPEND ZONE_PACKAGE_TARGETS zone_gpu)
endif()
set(ZONE_PACKAGE_DIR ${CMAKE_INSTALL_LIBDIR}/cmake/zone)

install(TARGETS ${ZONE_PACKAGE_TARGETS} EXPORT zone_targets
  ARCHIVE DESTINATION ${CMAKE_INSTALL_LIBDIR}
  LIBRARY DESTINATION ${CMAKE_INSTALL_LIBDIR}
  RUNTIME DESTINATION ${CMAKE_INSTALL_BINDIR}
  PUBLIC_HEADER DESTINATION ${CMAKE_INSTALL_INCLUDEDIR}/zone)
install(EXPORT zone_targets NAMESPACE zone:: FILE zoneTargets.cmake DESTINATION ${ZONE_PACKAGE_DIR})

set(ZONE_PACKAGE_HAS_GPU ${ZONE_HAVE_CUDA})
configure_package_config_file(${CMAKE_CURRENT_LIST_DIR}/zoneConfig.cmake.in
  ${PROJECT_BINARY_DIR}/package/zoneConfig.cmake INSTALL_DESTINATION ${ZONE_PACKAGE_DIR})
# 0.x: a minor version may break the API, so only the same minor version is compatible.
write_basic_package_version_file(${PROJECT_BINARY_DIR}/package/zoneConfigVersion.cmake
  VERSION ${PROJECT_VERSION} COMPATIBILITY SameMinorVersion)
install(FILES ${PROJECT_BINARY_DIR}/package/zoneConfig.cmake ${PROJECT_BINARY_DIR}/package/zoneConfigVersion.cmake
  DESTINATION ${ZONE_PACKAGE_DIR})

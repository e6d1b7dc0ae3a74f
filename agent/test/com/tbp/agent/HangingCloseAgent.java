package com.tbp.agent;

import java.util.concurrent.CountDownLatch;

/** An agent whose camera never finishes closing, run as its own process by {@link ExitDeadlineTest}. */
public final class HangingCloseAgent {

    private HangingCloseAgent() {
    }

    public static void main(String[] args) throws Exception {
        Fakes.Camera camera = new Fakes.Camera() {
            @Override
            public void close() {
                try {
                    new CountDownLatch(1).await();  // a HAL that never returns
                } catch (InterruptedException e) {
                    Thread.currentThread().interrupt();
                }
            }
        };
        System.exit(Launcher.run(args, new Fakes.FakePlatform(camera), System.in, System.out));
    }
}
